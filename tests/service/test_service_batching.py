"""Batching, queue limits, deadlines, disconnects, faults and the service lifecycle, through
httpx on the ASGI app. A gate on the real predictor holds the worker busy so that requests queue
deterministically."""

from __future__ import annotations

import base64
import io
import json
import logging
import threading
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import Any

import anyio
import httpx
import numpy as np
import pytest
import torch

from crestereo_pp.service.api.logs import JsonFormatter
from crestereo_pp.service.settings import Settings
from service_helpers import (
    Harness,
    assert_same_maps,
    lite_settings,
    metric_total,
    pair_files,
    serve_asgi,
    stereo_pair,
    wait_ready,
)

pytestmark = pytest.mark.anyio


def disparity_of(response: httpx.Response) -> np.ndarray:
    payload = response.json()["disparity"]
    return np.frombuffer(base64.b64decode(payload["data"]), "<f4").reshape(payload["shape"])


async def eventually(condition: Callable[[], bool], timeout_s: float = 30) -> None:
    with anyio.fail_after(timeout_s):
        while not condition():
            await anyio.sleep(0.005)


async def queue_depth(h: Harness, model: str = "lite") -> int:
    return (await h.client.get("/health")).json()["queue_depth"][model]


async def wait_queued(h: Harness, depth: int) -> None:
    with anyio.fail_after(30):
        while await queue_depth(h) != depth:
            await anyio.sleep(0.005)


class Requests:
    """Posts requests in the background and keeps their responses by name."""

    def __init__(self, h: Harness, tg: anyio.abc.TaskGroup) -> None:
        self.h, self.tg, self.responses = h, tg, {}

    def post(self, name: str, left: np.ndarray, right: np.ndarray, **kwargs: Any) -> None:
        async def send() -> None:
            self.responses[name] = await self.h.client.post("/disparity", files=pair_files(left, right), **kwargs)

        self.tg.start_soon(send)


@asynccontextmanager
async def worker_held(
    h: Harness, name: str = "busy", pair: tuple[np.ndarray, np.ndarray] | None = None
) -> AsyncIterator[Requests]:
    """Request `name` (of `pair`, default `stereo_pair()`) computing on the worker, held there by
    the gate until the body ends; the body posts more requests in the background, and every
    request is answered before the block exits."""
    gated = h.predictors["lite"]
    gated.gate.clear()
    async with anyio.create_task_group() as tg:
        requests = Requests(h, tg)
        requests.post(name, *(pair or stereo_pair()))
        await eventually(lambda: gated.calls == [1])
        try:
            yield requests
        finally:
            gated.gate.set()


async def test_requests_queued_behind_a_busy_worker_run_as_one_batch_equal_to_single_runs():
    # Three true sizes that all pad to 64x96: one-pass requests share one batch, each padded like the
    # network does (two-pass ones, "auto" included, batch by exact shape).
    pairs = {size: stereo_pair(*size, seed=i) for i, size in enumerate([(64, 96), (50, 90), (60, 70)])}
    async with serve_asgi() as h:
        gated = h.predictors["lite"]
        async with worker_held(h, pair=pairs[(64, 96)]) as requests:
            for size, pair in pairs.items():
                requests.post(size, *pair, params={"two_pass": "false"})
            await wait_queued(h, 3)
        metrics = (await h.client.get("/metrics")).text
        singles = {
            size: gated.predict(
                torch.from_numpy(np.stack([left])).permute(0, 3, 1, 2).float(),
                torch.from_numpy(np.stack([right])).permute(0, 3, 1, 2).float(),
                two_pass=False,
            )
            for size, (left, right) in pairs.items()
        }
    assert gated.calls[:2] == [1, 3]
    for size in pairs:
        response = requests.responses[size]
        assert response.status_code == 200
        assert response.json()["batch_size"] == 3 and response.headers["x-batch-size"] == "3"
        assert disparity_of(response).shape == size
        assert_same_maps(disparity_of(response), singles[size].disparity[0].numpy())
    assert metric_total(metrics, "crestereo_batch_size_count", model="lite") == 2
    assert metric_total(metrics, "crestereo_batch_size_sum", model="lite") == 4


async def test_batches_respect_max_batch_size_and_never_mix_shapes():
    small, large = stereo_pair(64, 96), stereo_pair(96, 64)
    async with serve_asgi(lite_settings(max_batch_size=2)) as h, worker_held(h, pair=small) as requests:
        for queued, (name, pair) in enumerate([("s1", small), ("l1", large), ("s2", small), ("s3", small)], start=1):
            requests.post(name, *pair)
            await wait_queued(h, queued)
    sizes = {name: r.json()["batch_size"] for name, r in requests.responses.items()}
    assert sizes == {"busy": 1, "s1": 2, "s2": 2, "l1": 1, "s3": 1}
    assert h.predictors["lite"].calls == [1, 2, 1, 1]


async def test_lite_and_full_never_share_a_batch():
    pair = stereo_pair()
    async with serve_asgi(Settings()) as h:  # the default settings serve both models
        lite, full = h.predictors["lite"], h.predictors["full"]
        async with worker_held(h, pair=pair) as requests:
            requests.post("lite", *pair)
            await eventually(lambda: requests_queued(h) == 1)
            requests.post("full", *pair, params={"model": "full"})
            await eventually(lambda: requests_queued(h) == 2)
        health = (await h.client.get("/health")).json()
    assert set(health["models"]) == {"lite", "full"}
    assert health["models"]["full"]["parameters"] > health["models"]["lite"]["parameters"]
    assert (lite.calls, full.calls) == ([1, 1], [1])
    for name in ("lite", "full"):
        response = requests.responses[name]
        assert response.status_code == 200
        assert (response.json()["model"], response.json()["batch_size"]) == (name, 1)


async def test_a_deadline_counts_the_work_of_every_model_queued_ahead_on_the_one_inference_thread():
    pair = stereo_pair()
    async with serve_asgi(Settings()) as h:  # lite and full, computed by one inference thread
        for model in ("lite", "full"):  # each model's compute time measured once
            measured = await h.client.post("/disparity", params={"model": model}, files=pair_files(*pair))
            assert measured.status_code == 200
            h.predictors[model].calls.clear()
        async with worker_held(h, pair=pair) as requests:
            for number in range(4):
                requests.post(f"full {number}", *pair, params={"model": "full"})
            await eventually(lambda: requests_queued(h) == 4)
            ahead = h.app.state.runtime.batcher.work_ahead_s("lite")
            refused = await h.client.post(
                "/disparity", files=pair_files(*pair), headers={"X-Request-Timeout-Ms": "500"}
            )
    assert ahead is not None and ahead > 0.5  # four of full's requests, each a few tenths of a second here
    assert refused.status_code == 503 and refused.json()["error"]["code"] == "deadline_exceeded"
    assert "cannot be met" in refused.json()["error"]["message"]  # at once, at admission
    assert int(refused.headers["retry-after"]) >= 1
    assert h.predictors["lite"].calls == [1] and sum(h.predictors["full"].calls) == 4  # the refused one never computed


def requests_queued(h: Harness) -> int:
    return sum(h.app.state.runtime.batcher.queue_depths().values())


async def test_a_full_queue_answers_503_with_retry_after_and_the_requests_it_holds_get_their_maps():
    async with serve_asgi(lite_settings(max_queue=1, max_batch_size=1)) as h:
        async with worker_held(h) as requests:
            requests.post("queued", *stereo_pair())
            await wait_queued(h, 1)
            refused = await h.client.post("/disparity", files=pair_files(*stereo_pair()))
        metrics = (await h.client.get("/metrics")).text
        left, right = (torch.from_numpy(image[None]).permute(0, 3, 1, 2).float() for image in stereo_pair())
        alone = h.predictors["lite"].predict(left, right).disparity[0].numpy()
    assert refused.status_code == 503
    assert refused.json()["error"]["code"] == "queue_full"
    assert int(refused.headers["retry-after"]) >= 1
    for name in ("busy", "queued"):  # the one computing and the one waiting both get the pair's own maps
        response = requests.responses[name]
        assert response.status_code == 200 and response.json()["batch_size"] == 1
        assert_same_maps(disparity_of(response), alone)
    assert metric_total(metrics, "crestereo_rejected_total", reason="queue_full") == 1


async def test_a_request_whose_deadline_passes_in_the_queue_gets_503_and_is_never_computed():
    async with serve_asgi() as h:
        async with worker_held(h) as requests:
            late = await h.client.post(
                "/disparity", files=pair_files(*stereo_pair()), headers={"X-Request-Timeout-Ms": "100"}
            )
            assert await queue_depth(h) == 0  # it left the queue when it gave up
        metrics = (await h.client.get("/metrics")).text
    assert late.status_code == 503
    assert late.json()["error"]["code"] == "deadline_exceeded"
    assert "retry-after" in late.headers
    assert requests.responses["busy"].status_code == 200
    assert h.predictors["lite"].calls == [1]
    assert metric_total(metrics, "crestereo_rejected_total", reason="deadline") == 1


async def test_a_request_whose_client_disconnected_is_dropped_before_compute():
    async with serve_asgi() as h:
        request = h.client.build_request("POST", "/disparity", files=pair_files(*stereo_pair()))
        body = request.read()
        scope = {
            "type": "http",
            "asgi": {"version": "3.0"},
            "http_version": "1.1",
            "method": "POST",
            "scheme": "http",
            "path": "/disparity",
            "raw_path": b"/disparity",
            "query_string": b"",
            "root_path": "",
            "headers": [(k.lower(), v) for k, v in request.headers.raw],
            "client": ("127.0.0.1", 50000),
            "server": ("service", 80),
        }
        messages = [{"type": "http.request", "body": body, "more_body": False}]

        async def receive() -> dict[str, Any]:  # the body, then the client is gone
            return messages.pop(0) if messages else {"type": "http.disconnect"}

        async def send(_: dict[str, Any]) -> None:
            pass

        await h.app(scope, receive, send)
        metrics = (await h.client.get("/metrics")).text
    assert h.predictors["lite"].calls == []
    assert metric_total(metrics, "crestereo_rejected_total", reason="disconnect") == 1


async def test_an_inference_exception_fails_only_its_batch_and_logs_an_error_id():
    black = np.zeros((64, 96, 3), np.uint8)  # the gated predictor raises on an all-black left image
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(JsonFormatter())
    async with serve_asgi() as h:
        logging.getLogger("crestereo_pp").addHandler(handler)  # after create_app set up logging
        try:
            async with worker_held(h, "before") as requests:
                requests.post("faulty", black, black, headers={"X-Request-Id": "faulty-1"})
                requests.post("other shape", *stereo_pair(96, 64))
                await wait_queued(h, 2)
            after = await h.client.post("/disparity", files=pair_files(*stereo_pair()))
            ready = await h.client.get("/health/ready")
        finally:
            logging.getLogger("crestereo_pp").removeHandler(handler)
    faulty = requests.responses["faulty"]
    assert faulty.status_code == 500
    assert faulty.json()["error"]["code"] == "inference_failed"
    error_id = faulty.json()["error"]["message"].rsplit(" ", 1)[-1]
    logged = [json.loads(line) for line in stream.getvalue().splitlines()]
    failure = next(line for line in logged if line.get("error_id") == error_id)
    assert failure["request_ids"] == ["faulty-1"] and "injected fault" in failure["traceback"]
    assert after.status_code == 200 and ready.status_code == 200
    # the batches beside the faulty one answered with their own pairs' maps (pairs under 192 px a
    # side take one pass by default)
    for name, (left, right) in {"before": stereo_pair(), "other shape": stereo_pair(96, 64)}.items():
        response = requests.responses[name]
        assert response.status_code == 200, response.text
        single = h.predictors["lite"].predict(
            torch.from_numpy(left[None]).permute(0, 3, 1, 2).float(),
            torch.from_numpy(right[None]).permute(0, 3, 1, 2).float(),
            two_pass=False,
        )
        assert_same_maps(disparity_of(response), single.disparity[0].numpy())


async def test_while_models_load_health_and_readiness_are_503_and_liveness_is_200():
    gate = threading.Event()
    async with serve_asgi(load_gate=gate, await_ready=False) as h:
        loading = {path: await h.client.get(path) for path in ("/health", "/health/ready", "/health/live")}
        refused = await h.client.post("/disparity", files=pair_files(*stereo_pair()))
        gate.set()
        await wait_ready(h.client)
        ready = await h.client.get("/health")
    assert loading["/health"].status_code == 503
    assert loading["/health"].json()["status"] == "loading"
    assert loading["/health"].json()["models"]["lite"] == {"loaded": False, "parameters": None, "weights": None}
    assert (loading["/health/ready"].status_code, loading["/health/ready"].json()) == (503, {"status": "loading"})
    assert loading["/health/live"].status_code == 200
    assert refused.status_code == 503 and refused.json()["error"]["code"] == "loading"
    assert "retry-after" in refused.headers
    health = ready.json()
    assert ready.status_code == 200 and health["status"] == "ready"
    assert health["models"]["lite"]["loaded"] is True
    assert health["models"]["lite"]["parameters"] == h.predictors["lite"].num_parameters
    assert health["queue_depth"] == {"lite": 0}
    assert health["batching"] == {
        "max_batch_size": 8,
        "max_batch_pixels": 131_072,
        "max_wait_ms": 10.0,
        "max_queue": 32,
        "torch_threads": health["batching"]["torch_threads"],
    }


async def test_models_that_fail_to_load_make_the_process_not_live():
    settings = lite_settings(weights={"lite": "/nonexistent/lite.pt"})
    async with serve_asgi(settings, await_ready=False) as h:
        await eventually(lambda: h.app.state.runtime.state == "failed")
        live = await h.client.get("/health/live")
        ready = await h.client.get("/health/ready")
        refused = await h.client.post("/disparity", files=pair_files(*stereo_pair()))
    assert (refused.status_code, refused.json()["error"]["code"]) == (503, "unavailable")
    assert (live.status_code, live.json()) == (503, {"status": "dead"})
    assert (ready.status_code, ready.json()) == (503, {"status": "failed"})


@asynccontextmanager
async def draining_with_work_admitted(settings: Settings | None = None) -> AsyncIterator[tuple[Harness, Requests]]:
    """A server draining (as after SIGTERM) with request "running" computing, held by the gate,
    and "queued" behind it; the body runs during the drain, then the gate opens (`worker_held`)."""
    async with serve_asgi(settings) as h, worker_held(h, "running") as requests:
        requests.post("queued", *stereo_pair())
        await wait_queued(h, 1)
        h.app.state.runtime.begin_drain()
        yield h, requests


async def test_draining_refuses_new_work_but_finishes_what_was_queued():
    async with draining_with_work_admitted() as (h, requests):
        refused = await h.client.post("/disparity", files=pair_files(*stereo_pair()))
        ready = await h.client.get("/health/ready")
        live = await h.client.get("/health/live")
    assert refused.status_code == 503 and refused.json()["error"]["code"] == "draining"
    assert (ready.status_code, ready.json()) == (503, {"status": "draining"})
    assert live.status_code == 200
    assert [requests.responses[n].status_code for n in ("running", "queued")] == [200, 200]


async def test_after_the_drain_timeout_queued_and_computing_requests_get_503():
    async with draining_with_work_admitted(lite_settings(drain_timeout_s=0.05)) as (_, requests):
        await eventually(lambda: {"queued", "running"} <= set(requests.responses))
    # the abandoned batch computes on once the gate opens; nobody waits for its result
    for name in ("running", "queued"):
        assert requests.responses[name].status_code == 503
        assert requests.responses[name].json()["error"]["code"] == "draining"


async def test_the_worker_runs_torch_with_the_configured_threads():
    process_threads = torch.get_num_threads()  # the app sets them process-wide: restore after
    async with serve_asgi(lite_settings(threads=1)) as h:
        seen: list[int] = []
        inner_predict_pairs = h.predictors["lite"]._inner.predict_pairs  # what the worker computes with

        def recording_predict_pairs(*args: Any, **kwargs: Any) -> Any:
            seen.append(torch.get_num_threads())
            return inner_predict_pairs(*args, **kwargs)

        h.predictors["lite"]._inner.predict_pairs = recording_predict_pairs
        response = await h.client.post("/disparity", files=pair_files(*stereo_pair()))
        health = (await h.client.get("/health")).json()
    torch.set_num_threads(process_threads)
    assert response.status_code == 200
    assert seen == [1] and health["batching"]["torch_threads"] == 1
