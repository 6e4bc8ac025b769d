"""Sharing a Ray cluster's CPUs among more workers or replicas than it has, on a real local cluster
of one CPU started in this process."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import pytest

from crestereo_pp.service.ray.cluster import cpu_share, cpu_threads, node_cpus, reserve_cpus

ray = pytest.importorskip("ray", reason="the `ray` extra is not installed")
from ray.util.placement_group import placement_group, remove_placement_group  # noqa: E402  (after the skip)
from ray.util.scheduling_strategies import PlacementGroupSchedulingStrategy  # noqa: E402

pytestmark = pytest.mark.slow  # a local Ray cluster, as tests/conftest.py marks the other Ray modules


@pytest.fixture(scope="module")
def one_cpu_cluster() -> Iterator[None]:
    ray.init(num_cpus=1, include_dashboard=False, logging_level=logging.WARNING)
    try:
        yield
    finally:
        ray.shutdown()


def test_three_workers_on_one_cpu_all_start_at_once_with_a_third_of_it_each(one_cpu_cluster):
    class Worker:  # defined here, so that Ray sends it to its workers by value
        """A worker that only says it started."""

        def ready(self) -> bool:
            return True

    share = cpu_share(3, node_cpus())
    assert share == 0.3333 and cpu_threads(share) == 1
    group = reserve_cpus(3, share, timeout_s=30)
    try:
        placed = PlacementGroupSchedulingStrategy(group)
        actor = ray.remote(num_cpus=share, scheduling_strategy=placed)(Worker)
        workers = [actor.remote() for _ in range(3)]
        assert ray.get([worker.ready.remote() for worker in workers], timeout=60) == [True] * 3
    finally:
        remove_placement_group(group)


def test_replicas_beyond_the_cpus_get_the_same_fractional_share_as_workers(one_cpu_cluster):
    from crestereo_pp.service.ray.serve import Scale

    assert Scale(replicas=3).cpus_per_replica() == 0.3333
    assert Scale(min_replicas=1, max_replicas=4).cpus_per_replica() == 0.25
    assert Scale(replicas=3, cpus=1).cpus_per_replica() == 1


def test_workers_the_cluster_has_no_free_cpus_for_are_refused_after_the_wait_saying_what_was_asked_and_what_it_has(
    one_cpu_cluster,
):
    busy = placement_group([{"CPU": 1}])
    assert busy.wait(timeout_seconds=30)
    try:
        with pytest.raises(ValueError) as refused:
            reserve_cpus(2, 0.5, timeout_s=1)
    finally:
        remove_placement_group(busy)
    assert str(refused.value) == (
        "2 worker(s) of 0.5 CPU(s) each (1 CPU(s) in all) could not be placed within 1 s: "
        "the cluster has 1 CPU(s) on 1 node(s) (1), 0 free"
    )
