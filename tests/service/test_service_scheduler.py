"""The batch scheduler's rules, driven directly through `Batcher.admit` with the real lite model."""

from __future__ import annotations

from collections.abc import AsyncIterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager

import anyio
import pytest

from service.batching import Batcher, JobResult, Knobs
from service.metrics import Metrics
from service_helpers import GatedPredictor, lite_settings, quiet_load_model, stereo_pair

pytestmark = pytest.mark.anyio
LEFT, RIGHT = stereo_pair()


async def connected() -> bool:
    return False


@asynccontextmanager
async def batcher(**settings: float) -> AsyncIterator[tuple[Batcher, GatedPredictor]]:
    predictor = GatedPredictor(quiet_load_model("lite"))
    with ThreadPoolExecutor(max_workers=1) as executor:
        batcher = Batcher(lite_settings(**settings), {"lite": predictor}, executor, Metrics(8))
        batcher.start()
        try:
            yield batcher, predictor
        finally:
            await batcher.close()


async def run(batcher: Batcher, results: list[JobResult]) -> None:
    async with batcher.admit("lite") as admission:
        results.append(await admission.run(LEFT, RIGHT, knobs=Knobs(), deadline=None,
                                           is_disconnected=connected))


async def test_an_idle_server_runs_a_lone_request_at_once_whatever_the_max_wait():
    results: list[JobResult] = []
    async with batcher(max_wait_ms=600_000) as (b, predictor):
        with anyio.fail_after(60):
            await run(b, results)
    assert predictor.calls == [1] and results[0].batch_size == 1


async def test_a_partial_batch_waits_for_requests_still_being_decoded():
    results: list[JobResult] = []
    async with batcher(max_wait_ms=600_000) as (b, predictor):
        with anyio.fail_after(60):
            async with b.admit("lite") as decoding, anyio.create_task_group() as tg:
                tg.start_soon(run, b, results)  # queued while `decoding` is still admitted
                await anyio.sleep(0.2)
                assert predictor.calls == []  # held back: another request is on its way
                results.append(await decoding.run(LEFT, RIGHT, knobs=Knobs(), deadline=None,
                                                  is_disconnected=connected))
    assert predictor.calls == [2] and [r.batch_size for r in results] == [2, 2]


async def test_a_partial_batch_runs_once_it_has_waited_max_wait():
    results: list[JobResult] = []
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
                results: list[JobResult] = []
                tg.start_soon(run, b, results)
                while predictor.calls != [1]:
                    await anyio.sleep(0.005)
                with anyio.move_on_after(0.05):  # the client gives up while queued
                    await run(b, [])
                assert b.queue_depths() == {"lite": 0}
                predictor.gate.set()
            await run(b, results)
    assert predictor.calls == [1, 1] and len(results) == 2
