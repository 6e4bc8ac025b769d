"""The batch scheduler: the choice of the next batch and the compute-time statistics as pure units
(no event loop, no model), then its rules driven through `Batcher.admit` with the real lite model."""

from __future__ import annotations

from collections.abc import AsyncIterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager
from dataclasses import dataclass

import anyio
import pytest

from crestereo_pp.inference import InferenceOptions
from crestereo_pp.service.api.metrics import Metrics
from crestereo_pp.service.batching.batcher import Batcher, JobResult
from crestereo_pp.service.batching.policy import BatchLimits, ComputeTimes, choose_batch
from crestereo_pp.service.batching.stereo import (
    StereoBatches,
    StereoKey,
    StereoMaps,
    StereoPair,
    relative_cost,
    stereo_key,
)
from service_helpers import GatedPredictor, lite_settings, quiet_load_model, stereo_pair

pytestmark = pytest.mark.anyio  # the async tests; the sync ones ignore it
LEFT, RIGHT = stereo_pair()

# --- the choice of the next batch (pure) -------------------------------------------------------

LIMITS = BatchLimits(max_batch_size=3, max_batch_pixels=64 * 96 * 3, max_wait_s=0.010)
SMALL = stereo_key("lite", InferenceOptions(), 64, 96)
LARGE = stereo_key("lite", InferenceOptions(), 128, 192)  # twice as large each way: one per batch


@dataclass(frozen=True)
class QueuedRequest:
    key: StereoKey
    enqueued_at: float


def queue(*requests: tuple[StereoKey, float]) -> list[QueuedRequest]:
    return [QueuedRequest(key, at) for key, at in requests]


def test_nothing_queued_means_nothing_to_run_and_no_timeout():
    assert choose_batch([], incoming=2, now=5.0, limits=LIMITS) == ([], None)


def test_a_lone_request_runs_at_once_when_nothing_else_is_incoming():
    queued = queue((SMALL, 1.0))
    assert choose_batch(queued, incoming=0, now=1.0, limits=LIMITS) == (queued, None)


def test_a_partial_batch_waits_for_incoming_requests_until_its_oldest_has_waited_max_wait():
    queued = queue((SMALL, 1.0), (SMALL, 1.002))
    batch, wait_s = choose_batch(queued, incoming=1, now=1.004, limits=LIMITS)
    assert batch == [] and wait_s == pytest.approx(0.006)
    assert choose_batch(queued, incoming=1, now=1.011, limits=LIMITS) == (queued, None)


def test_a_full_group_runs_before_an_older_partial_one_that_has_not_waited_long():
    older = queue((stereo_key("lite", InferenceOptions(two_pass=True), 64, 96), 1.0))
    full = queue((SMALL, 1.001), (SMALL, 1.002), (SMALL, 1.003))
    assert choose_batch(older + full, incoming=1, now=1.004, limits=LIMITS) == (full, None)
    # ... but once the older group has waited max_wait it goes first
    assert choose_batch(older + full, incoming=1, now=1.011, limits=LIMITS) == (older, None)


def test_a_batch_takes_the_oldest_requests_of_its_group_up_to_its_capacity():
    queued = queue((SMALL, 1.004), (SMALL, 1.001), (SMALL, 1.003), (SMALL, 1.002))
    batch, _ = choose_batch(queued, incoming=0, now=1.005, limits=LIMITS)
    assert [request.enqueued_at for request in batch] == [1.001, 1.002, 1.003]  # max_batch_size 3


def test_the_pixel_limit_caps_a_batch_and_a_larger_image_runs_alone():
    assert LIMITS.capacity(SMALL) == 3
    assert LIMITS.capacity(stereo_key("lite", InferenceOptions(), 64, 192)) == 1  # the pixel limit: 1.5 fit
    assert LIMITS.capacity(LARGE) == 1  # beyond the pixel limit: alone, never refused
    queued = queue((LARGE, 1.0), (LARGE, 1.001))
    assert choose_batch(queued, incoming=0, now=1.002, limits=LIMITS) == (queued[:1], None)


def test_models_options_and_shapes_never_share_a_batch():
    others = [
        stereo_key("full", InferenceOptions(), 64, 96),
        stereo_key("lite", InferenceOptions(iters=4), 64, 96),
        stereo_key("lite", InferenceOptions(), 96, 64),
    ]
    queued = queue((SMALL, 1.0), *((key, 1.001 + i / 1000) for i, key in enumerate(others)), (SMALL, 1.005))
    batch, _ = choose_batch(queued, incoming=0, now=1.006, limits=LIMITS)
    assert batch == [queued[0], queued[-1]]


def test_one_pass_requests_batch_by_padded_shape_two_pass_auto_and_scaled_ones_by_exact_shape():
    one_pass = InferenceOptions(two_pass=False)
    plain = stereo_key("lite", one_pass, 50, 90)
    assert plain == stereo_key("lite", one_pass, 64, 96) and (plain.height, plain.width) == (64, 96)
    for options in (InferenceOptions(), InferenceOptions(two_pass=True), InferenceOptions(scale=0.5)):
        assert stereo_key("lite", options, 50, 90) != stereo_key("lite", options, 64, 96)
        assert stereo_key("lite", options, 50, 90).pixels == 50 * 90


# --- compute-time statistics (pure) ------------------------------------------------------------


def test_compute_times_are_unknown_before_the_first_batch_then_exact_for_it():
    times = ComputeTimes()
    assert times.get("lite") is None
    times.record("lite", work=1000, batch_size=4, seconds=2.0)
    lite = times.get("lite")
    assert lite is not None
    assert (lite.seconds_per_work, lite.work_per_request) == (0.0005, 1000.0)
    assert lite.seconds(3000) == pytest.approx(1.5)
    assert times.get("full") is None  # one model's batches say nothing about another's


def test_compute_times_are_running_means_weighting_the_newest_batch():
    times = ComputeTimes(weight=0.25)
    times.record("lite", work=1000, batch_size=1, seconds=1.0)
    times.record("lite", work=3000, batch_size=1, seconds=15.0)  # 0.005 s per unit
    lite = times.get("lite")
    assert lite is not None
    assert lite.seconds_per_work == pytest.approx(0.75 * 0.001 + 0.25 * 0.005)
    assert lite.work_per_request == pytest.approx(0.75 * 1000 + 0.25 * 3000)


def test_the_cost_of_a_request_follows_its_iterations_scale_and_flip():
    lite = (2, 4, 6)
    assert relative_cost(lite, lite, scale=1.0, two_pass=False) == 1.0
    assert relative_cost((99, 99, 99), lite, scale=1.0, two_pass=False) > 10  # the flood that once froze estimates
    assert relative_cost((1, 1, 1), lite, scale=1.0, two_pass=False) < 0.5
    # the network sees a quarter of the pixels; the classical steps and the maps' resampling do not shrink
    assert relative_cost(lite, lite, scale=0.5, two_pass=False) == pytest.approx(0.3 + 0.7 * 0.25)
    assert relative_cost(lite, lite, scale=0.5, two_pass=False, flip=True) == pytest.approx(2 * 0.475)  # all twice


def test_costly_requests_neither_skew_the_estimate_of_plain_ones_nor_are_underestimated():
    times = ComputeTimes()
    plain = relative_cost((2, 4, 6), (2, 4, 6), 1.0, False) * 1000
    heavy = relative_cost((99, 99, 99), (2, 4, 6), 1.0, False) * 1000
    times.record("lite", work=plain, batch_size=1, seconds=0.2)
    for _ in range(5):  # five heavy batches, each taking its true time at the same rate
        times.record("lite", work=heavy, batch_size=1, seconds=0.2 * heavy / plain)
    lite = times.get("lite")
    assert lite is not None
    assert lite.seconds(plain) == pytest.approx(0.2)
    assert lite.seconds(heavy) == pytest.approx(0.2 * heavy / plain)


# --- through Batcher.admit ----------------------------------------------------------------------


async def connected() -> bool:
    return False


@asynccontextmanager
async def batcher(
    **settings: float,
) -> AsyncIterator[tuple[Batcher[StereoKey, StereoPair, StereoMaps], GatedPredictor]]:
    predictor = GatedPredictor(quiet_load_model("lite"))
    with ThreadPoolExecutor(max_workers=1) as executor:
        batcher = Batcher(lite_settings(**settings), StereoBatches({"lite": predictor}), executor, Metrics(8))
        batcher.start()
        try:
            yield batcher, predictor
        finally:
            await batcher.close()


PLAIN = stereo_key("lite", InferenceOptions(), *LEFT.shape[:2])


async def run(batcher: Batcher[StereoKey, StereoPair, StereoMaps], results: list[JobResult[StereoMaps]]) -> None:
    async with batcher.admit("lite") as admission:
        results.append(await admission.run(PLAIN, StereoPair(LEFT, RIGHT), deadline=None, is_disconnected=connected))


async def test_an_idle_server_runs_a_lone_request_at_once_whatever_the_max_wait():
    results: list[JobResult[StereoMaps]] = []
    async with batcher(max_wait_ms=600_000) as (b, predictor):
        with anyio.fail_after(60):
            await run(b, results)
    assert predictor.calls == [1] and results[0].batch_size == 1


async def test_a_partial_batch_waits_for_requests_still_being_decoded():
    results: list[JobResult[StereoMaps]] = []
    async with batcher(max_wait_ms=600_000) as (b, predictor):
        with anyio.fail_after(60):
            async with b.admit("lite") as decoding, anyio.create_task_group() as tg:
                tg.start_soon(run, b, results)  # queued while `decoding` is still admitted
                await anyio.sleep(0.2)
                assert predictor.calls == []  # held back: another request is on its way
                results.append(
                    await decoding.run(PLAIN, StereoPair(LEFT, RIGHT), deadline=None, is_disconnected=connected)
                )
    assert predictor.calls == [2] and [r.batch_size for r in results] == [2, 2]


async def test_a_partial_batch_runs_once_it_has_waited_max_wait():
    results: list[JobResult[StereoMaps]] = []
    async with batcher(max_wait_ms=50) as (b, predictor):
        with anyio.fail_after(60):
            async with b.admit("lite"):  # admitted, but never queued
                await run(b, results)
    assert predictor.calls == [1] and results[0].batch_size == 1


async def test_a_request_that_leaves_while_queued_frees_its_place():
    async with batcher(max_queue=1) as (b, predictor):
        predictor.gate.clear()
        with anyio.fail_after(60):
            async with anyio.create_task_group() as tg:
                results: list[JobResult[StereoMaps]] = []
                tg.start_soon(run, b, results)
                while predictor.calls != [1]:
                    await anyio.sleep(0.005)
                with anyio.move_on_after(0.05):  # the client gives up while queued
                    await run(b, [])
                assert b.queue_depths() == {"lite": 0}
                predictor.gate.set()
            await run(b, results)
    assert predictor.calls == [1, 1] and len(results) == 2
