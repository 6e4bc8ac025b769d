"""The CPU share the service sizes its threads by: the cgroup quota, else the cores."""

from __future__ import annotations

import os

from crestereo_pp.service.batching.cpu import cgroup_cpu_quota, usable_cpus


def test_cpu_quota_is_read_from_cgroup_v2(tmp_path):
    (tmp_path / "cpu.max").write_text("250000 100000\n")
    assert cgroup_cpu_quota(tmp_path) == 2.5
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert cgroup_cpu_quota(tmp_path) is None


def test_cpu_quota_is_read_from_cgroup_v1(tmp_path):
    (tmp_path / "cpu").mkdir()
    (tmp_path / "cpu" / "cpu.cfs_period_us").write_text("100000\n")
    (tmp_path / "cpu" / "cpu.cfs_quota_us").write_text("150000\n")
    assert cgroup_cpu_quota(tmp_path) == 1.5
    (tmp_path / "cpu" / "cpu.cfs_quota_us").write_text("-1\n")
    assert cgroup_cpu_quota(tmp_path) is None


def test_usable_cpus_round_the_quota_down_and_fall_back_to_the_cores(tmp_path):
    cores = len(os.sched_getaffinity(0))
    assert usable_cpus(tmp_path) == cores  # no cgroup files: the cores we may run on
    (tmp_path / "cpu.max").write_text("50000 100000\n")
    assert usable_cpus(tmp_path) == 1
    (tmp_path / "cpu.max").write_text(f"{(cores + 8) * 100000} 100000\n")
    assert usable_cpus(tmp_path) == cores
