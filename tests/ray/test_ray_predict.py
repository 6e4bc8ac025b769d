"""`crestereo-pp predict --ray`: folders of real pairs as a Ray job on a local cluster (lite on
torch, two workers), against the plain command."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from ray_helpers import write_pairs

from crestereo_pp.cli.main import main
from crestereo_pp.stereo_data.formats import read_pfm
from service_helpers import REPO, assert_same_maps

pytest.importorskip("ray", reason="the `ray` extra is not installed")


def ray_job(lefts: Path, rights: Path, out: Path, *extra: str, one_cpu: bool = False) -> subprocess.Popen[str]:
    """The command on a local cluster of this machine's CPUs (of one of them: `one_cpu`), two workers
    unless `extra` says otherwise."""

    def child_setup() -> None:
        # Ctrl-C acts as at a terminal whatever this process inherited or set (an ignored SIGINT is inherited)
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        if one_cpu:  # the command, and the cluster it starts, see one CPU
            os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})

    command = [
        sys.executable,
        "-m",
        "crestereo_pp.cli.main",
        "predict",
        str(lefts),
        str(rights),
        "-o",
        str(out / "disparity"),
    ]
    command += ["--uncertainty", str(out / "uncertainty"), "--mkdir", "--backend", "torch", "--ray", "--workers", "2"]
    environment = {**os.environ, "PYTHONWARNINGS": "ignore::RuntimeWarning"}
    return subprocess.Popen(
        [*command, *extra],
        cwd=REPO,
        env=environment,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        preexec_fn=child_setup,
    )


def finished(job: subprocess.Popen[str]) -> tuple[int, str]:
    output, _ = job.communicate(timeout=600)
    return job.returncode, output


def test_the_ray_job_writes_the_plain_commands_maps_and_reports_a_bad_pair_without_stopping(tmp_path: Path):
    lefts, rights = write_pairs(tmp_path / "pairs", 4)
    right = cv2.imread(str(rights / "pair_01.png"))  # one pair's right rows 1.5 px off its left's
    moved = cv2.warpAffine(right, np.float32([[1, 0, 0], [0, 1, 1.5]]), right.shape[1::-1])
    cv2.imwrite(str(rights / "pair_01.png"), moved)
    plain = tmp_path / "plain"
    assert main(["predict", str(lefts), str(rights), "-o", str(plain), "--mkdir", "--backend", "torch"]) == 0
    (lefts / "pair_99.png").write_bytes(b"not an image")
    (rights / "pair_99.png").write_bytes(b"not an image")

    status, output = finished(ray_job(lefts, rights, tmp_path / "ray"))

    assert status == 1, output  # a pair failed
    assert "computed 4 pair(s)" in output and "failed 1" in output
    assert "lay 1 px or more off the left's in 1 of 4 pairs (up to 1." in output, output  # 1.5 and the crop's own
    assert re.search(r"failed \S*pair_99\.png \S*pair_99\.png: FormatError: .*cannot be decoded", output), output
    for index in range(4):
        computed = read_pfm(tmp_path / "ray" / "disparity" / f"pair_{index:02d}.pfm")
        assert_same_maps(computed, read_pfm(plain / f"pair_{index:02d}.pfm"))
        assert (tmp_path / "ray" / "uncertainty" / f"pair_{index:02d}.pfm").is_file()
    assert not (tmp_path / "ray" / "disparity" / "pair_99.pfm").exists()


def test_more_workers_than_cpus_all_start_with_an_equal_fraction_of_them(tmp_path: Path):
    lefts, rights = write_pairs(tmp_path / "pairs", 2)

    status, output = finished(ray_job(lefts, rights, tmp_path / "out", one_cpu=True))  # two workers

    assert status == 0, output
    assert "2 worker(s) of 0.5 CPU(s) ready" in output, output
    assert "computed 2 pair(s)" in output


def test_an_interrupted_job_run_again_computes_only_the_pairs_it_had_not_finished(tmp_path: Path):
    count = 12
    lefts, rights = write_pairs(tmp_path / "pairs", count)
    out = tmp_path / "out"
    job = ray_job(lefts, rights, out)
    deadline = time.monotonic() + 300
    while not list((out / "uncertainty").glob("*.pfm")):
        assert job.poll() is None and time.monotonic() < deadline, "no pair was written"
        time.sleep(0.05)
    job.send_signal(signal.SIGINT)
    status, output = finished(job)
    done = [
        index
        for index in range(count)
        if all((out / kind / f"pair_{index:02d}.pfm").is_file() for kind in ("disparity", "uncertainty"))
    ]
    assert status == 130 and "interrupted" in output, output
    assert 0 < len(done) < count, output

    status, output = finished(ray_job(lefts, rights, out))

    assert status == 0, output
    assert f"skipping {len(done)} pair(s)" in output
    assert f"computed {count - len(done)} pair(s)" in output
    for kind in ("disparity", "uncertainty"):
        assert sorted(path.name for path in (out / kind).iterdir()) == [f"pair_{i:02d}.pfm" for i in range(count)]
