"""Spec of the decoder processes (`service.decoding`): uploads are parsed and decoded in worker
processes with a memory cap and a CPU-time limit per job; a breach or an abandoned job costs
only that process, which is replaced, and the server's event loop keeps running meanwhile."""

from __future__ import annotations

import asyncio
import time

import cv2
import httpx
import numpy as np
import pytest

from service.batching import ClientDisconnected
from service.decoding import DecoderLimits, DecoderPool
from service.images import read_header
from service.uploads import ImageLimits, UploadError
from service_helpers import encode, lite_settings, serve_asgi, stereo_pair

pytestmark = pytest.mark.anyio

GENEROUS = DecoderLimits(workers=1, memory_bytes=768 << 20, cpu_seconds=5.0)
LIMITS = ImageLimits(model="lite", max_pixels=4_194_304, min_side=32)


async def never() -> Exception:
    await asyncio.sleep(3600)
    raise AssertionError("unreachable")


def large_progressive_jpeg(side: int = 2000) -> bytes:
    noise = np.random.default_rng(0).integers(0, 256, (side, side, 3), dtype=np.uint8)
    return cv2.imencode(".jpg", noise, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1].tobytes()


def multipart(files: dict[str, tuple[str, bytes, str]]) -> tuple[bytes, str]:
    """The body and Content-Type that httpx sends for these files."""
    request = httpx.Request("POST", "http://x/disparity", files=files)
    return request.read(), request.headers["content-type"]


async def started(limits: DecoderLimits) -> DecoderPool:
    pool = DecoderPool(limits)
    await pool.start()
    return pool


async def test_the_pool_parses_the_form_and_decodes_the_pair_exactly():
    left, right = stereo_pair()
    body, content_type = multipart(
        {"left": ("l.png", encode(left), "image/png"), "right": ("r.png", encode(right), "image/png")}
    )
    pool = await started(GENEROUS)
    try:
        upload = await pool.read_pair(body, content_type, LIMITS, never)
        decoded = await pool.decode_pair(upload.left, upload.right, upload.header, never)
    finally:
        await pool.close()
    assert (upload.header.width, upload.header.height) == (left.shape[1], left.shape[0])
    assert upload.rig is None  # a rectified pair
    assert np.array_equal(decoded[0], left) and np.array_equal(decoded[1], right)


@pytest.mark.parametrize(
    ("files", "code"),
    [
        ({}, "missing_field"),
        ({"model": ("m.txt", b"full", "text/plain")}, "unknown_field"),
    ],
)
async def test_a_form_that_is_not_two_images_is_refused_by_name(files, code):
    _, right = stereo_pair()
    body, content_type = multipart({**files, "right": ("r.png", encode(right), "image/png")})
    pool = await started(GENEROUS)
    try:
        with pytest.raises(UploadError) as refused:
            await pool.read_pair(body, content_type, LIMITS, never)
        assert refused.value.status == 422 and refused.value.code == code
        assert pool.restarts == 0  # a refusal is an answer, not a breach
    finally:
        await pool.close()


async def test_a_decode_beyond_its_memory_answers_413_and_the_process_is_replaced():
    rgba16 = np.full((2048, 2048, 4), 1000, dtype=np.uint16)
    heavy = cv2.imencode(".png", rgba16)[1].tobytes()  # a small file of 34 MB of pixels, then conversions
    pool = await started(DecoderLimits(workers=1, memory_bytes=64 << 20, cpu_seconds=5.0))
    try:
        with pytest.raises(UploadError) as refused:
            await pool.decode_pair(heavy, heavy, read_header(heavy), never)
        assert (refused.value.status, refused.value.code) == (413, "decode_too_large"), refused.value
        left, right = stereo_pair()
        images = await pool.decode_pair(encode(left), encode(right), read_header(encode(left)), never)
        assert np.array_equal(images[0], left)
        assert pool.restarts == 1
    finally:
        await pool.close()


async def test_a_decode_beyond_its_cpu_time_answers_422_while_the_event_loop_keeps_running():
    costly = large_progressive_jpeg()
    pool = await started(DecoderLimits(workers=1, memory_bytes=768 << 20, cpu_seconds=0.05))
    ticks = 0

    async def ticker() -> None:
        nonlocal ticks
        while True:
            await asyncio.sleep(0.01)
            ticks += 1

    ticking = asyncio.ensure_future(ticker())
    try:
        started_at = time.monotonic()
        with pytest.raises(UploadError) as refused:
            await pool.decode_pair(costly, costly, read_header(costly), never)
        elapsed = time.monotonic() - started_at
        assert (refused.value.status, refused.value.code) == (422, "decode_too_costly"), refused.value
        assert ticks >= elapsed / 0.01 / 3  # the loop was never held up by the decode
        left, right = stereo_pair()
        images = await pool.decode_pair(encode(left), encode(right), read_header(encode(left)), never)
        assert np.array_equal(images[1], right)
    finally:
        ticking.cancel()
        await pool.close()


async def test_an_abandoned_job_stops_at_once_and_costs_only_its_process():
    costly = large_progressive_jpeg()
    pool = await started(GENEROUS)

    async def client_leaves() -> Exception:
        await asyncio.sleep(0.05)
        return ClientDisconnected("client left")

    try:
        started_at = time.monotonic()
        with pytest.raises(ClientDisconnected):
            await pool.decode_pair(costly, costly, read_header(costly), client_leaves)
        assert time.monotonic() - started_at < 0.5  # decoding both takes over a second here
        assert pool.restarts == 1
        images = await pool.decode_pair(costly, costly, read_header(costly), never)
        assert images[0].shape == (2000, 2000, 3)
    finally:
        await pool.close()


async def test_a_request_still_reading_its_images_when_the_drain_ends_gets_503_draining():
    costly = large_progressive_jpeg()
    files = {"left": ("l.jpg", costly, "image/jpeg"), "right": ("r.jpg", costly, "image/jpeg")}
    async with serve_asgi(lite_settings(drain_timeout_s=0.1)) as h:
        runtime = h.app.state.runtime
        posting = asyncio.ensure_future(h.client.post("/disparity", files=files))
        await asyncio.sleep(0.3)  # the request is admitted and its images are being decoded (over a second)
        assert not posting.done()
        started_at = time.monotonic()
        runtime.begin_drain()
        answer = await posting
    assert answer.status_code == 503 and answer.json()["error"]["code"] == "draining"
    assert time.monotonic() - started_at < 1.0  # the decode was stopped, not waited for
