"""Spec of the decoder processes (`service.uploads.sandbox`): uploads are parsed and decoded in
processes with a memory cap and a CPU-time limit per job; a breach or an abandoned job costs
only that process, which is replaced, and the server's event loop keeps running meanwhile."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import struct
import time
import zlib
from collections.abc import Iterator
from pathlib import Path

import anyio
import cv2
import httpx
import numpy as np
import pytest

from crestereo_pp.service.batching.batcher import ClientDisconnected
from crestereo_pp.service.uploads.images import read_header
from crestereo_pp.service.uploads.multipart import ImageLimits, UploadError
from crestereo_pp.service.uploads.sandbox import DecoderLimits, DecoderPool
from service_helpers import (
    Server,
    corrupt_jpeg,
    encode,
    lite_settings,
    pair_files,
    run_uvicorn,
    serve_asgi,
    stereo_pair,
)

pytestmark = pytest.mark.anyio

GENEROUS = DecoderLimits(processes=1, memory_bytes=768 << 20, cpu_seconds=5.0)
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
    pool = await started(DecoderLimits(processes=1, memory_bytes=64 << 20, cpu_seconds=5.0))
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
    pool = await started(DecoderLimits(processes=1, memory_bytes=768 << 20, cpu_seconds=0.05))
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


async def test_an_abandoned_job_is_answered_at_once_and_its_decoder_finishes_it_unharmed():
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
        images = await pool.decode_pair(costly, costly, read_header(costly), never)  # after the dropped one
        assert images[0].shape == (2000, 2000, 3)
        assert pool.restarts == 0
    finally:
        await pool.close()


class KilledDuringJobs(DecoderPool):
    """A pool whose next `kills` jobs lose their process to SIGKILL from outside as they are
    handed over (after the ping that found it healthy)."""

    def __init__(self, limits: DecoderLimits, kills: int) -> None:
        super().__init__(limits)
        self.kills = kills

    async def _exchange(self, process, meta, buffers):
        if meta["job"] != "ping" and self.kills:
            self.kills -= 1
            process.kill()
        return await super()._exchange(process, meta, buffers)


@pytest.mark.parametrize("kills", [1, 2])
async def test_a_job_whose_decoder_is_killed_from_outside_runs_again_and_a_second_loss_is_the_uploads(kills):
    left, right = stereo_pair()
    pool = KilledDuringJobs(GENEROUS, kills)
    await pool.start()
    try:
        if kills == 1:
            images = await pool.decode_pair(encode(left), encode(right), read_header(encode(left)), never)
            assert np.array_equal(images[0], left)
        else:
            with pytest.raises(UploadError) as refused:
                await pool.decode_pair(encode(left), encode(right), read_header(encode(left)), never)
            assert (refused.value.status, refused.value.code) == (422, "undecodable_image")
            assert "status -9" in refused.value.message
        assert pool.restarts == kills
    finally:
        await pool.close()


async def test_a_jpeg_with_corrupt_data_is_refused_in_its_decoder_process_naming_the_corruption():
    left, right = stereo_pair()
    broken = corrupt_jpeg(left)
    pool = DecoderPool(GENEROUS)
    await pool.start()
    try:
        with pytest.raises(UploadError) as refused:
            await pool.decode_pair(broken, encode(right, ".jpg"), read_header(broken), never)
        images = await pool.decode_pair(encode(left, ".jpg"), encode(right, ".jpg"), read_header(broken), never)
    finally:
        await pool.close()
    assert (refused.value.status, refused.value.code) == (422, "undecodable_image")
    assert refused.value.message.startswith("left: the image is a corrupt JPEG (Corrupt JPEG data:")
    assert images[0].shape == left.shape  # the same decoder goes on decoding intact JPEGs


def png_claiming(image: np.ndarray, width: int, height: int) -> bytes:
    """`image` as a PNG whose header says it is `width` x `height` (its CRC made right). Fewer rows
    than it holds: libpng decodes those and warns "IDAT: Too much image data"; another width: the
    rows no longer parse, and libpng fails ("bad adaptive filter value")."""
    png = bytearray(encode(image))
    header = bytearray(png[16:29])  # IHDR's data: width, height, ...
    header[0:8] = struct.pack(">II", width, height)
    png[16:29], png[29:33] = header, struct.pack(">I", zlib.crc32(b"IHDR" + bytes(header)))
    return bytes(png)


async def test_what_a_decoder_prints_goes_to_the_logs_as_json_and_a_failure_says_why(caplog, capfd):
    left, right = stereo_pair()
    height, width = left.shape[:2]
    too_much, narrow = png_claiming(left, width, height // 2), png_claiming(left, width // 2, height)
    pool = DecoderPool(GENEROUS)
    await pool.start()
    try:
        with caplog.at_level(logging.WARNING, logger="crestereo_pp.service.uploads.sandbox"):
            images = await pool.decode_pair(too_much, encode(right[: height // 2]), read_header(too_much), never)
            for _ in range(100):  # the line reaches the log from the process's stderr, soon after the answer
                if any("Too much image data" in record.getMessage() for record in caplog.records):
                    break
                await asyncio.sleep(0.02)
        with pytest.raises(UploadError) as refused:
            await pool.decode_pair(narrow, encode(right[:, : width // 2]), read_header(narrow), never)
    finally:
        await pool.close()
    assert np.array_equal(images[0], left[: height // 2])
    assert [r.getMessage() for r in caplog.records if "decoder process wrote" in r.getMessage()] == [
        "decoder process wrote: libpng warning: IDAT: Too much image data"
    ]
    assert "libpng" not in capfd.readouterr().err  # nothing raw beside the JSON logs
    assert refused.value.code == "undecodable_image"
    assert refused.value.message.startswith("left: the image cannot be decoded (libpng error: ")


def waiting_decoders(parent: int) -> list[int]:
    """The decoder processes that `parent` started and that wait for a job (read their pipe)."""
    pids = []
    for task in Path(f"/proc/{parent}/task").iterdir():
        try:
            children = (task / "children").read_text().split()
        except FileNotFoundError:  # a thread that ended since the listing
            continue
        for pid in children:
            with contextlib.suppress(FileNotFoundError):
                waiting = "pipe_read" in Path(f"/proc/{pid}/wchan").read_text()
                if waiting and b"crestereo_pp.service.uploads.sandbox" in Path(f"/proc/{pid}/cmdline").read_bytes():
                    pids.append(int(pid))
    return sorted(pids)


async def test_idle_decoders_killed_or_stopped_from_outside_cost_the_next_jobs_nothing():
    left, right = stereo_pair()
    files = encode(left), encode(right)
    pool = await started(DecoderLimits(processes=2, memory_bytes=768 << 20, cpu_seconds=5.0))
    try:
        with anyio.fail_after(60):
            while len(waiting_decoders(os.getpid())) < 2:
                await asyncio.sleep(0.05)
        killed, stopped = waiting_decoders(os.getpid())
        os.kill(killed, signal.SIGKILL)
        os.kill(stopped, signal.SIGSTOP)
        started_at = time.monotonic()
        for _ in range(2):
            images = await pool.decode_pair(*files, read_header(files[0]), never)
            assert np.array_equal(images[1], right)
        assert time.monotonic() - started_at < 10  # a ping of 1 s, not the wall limit of 22 s
        assert pool.restarts == 2
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


# --- on a real server ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def own_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """A server of these tests' own, whose decoders they kill and stop."""
    with run_uvicorn(tmp_path_factory.mktemp("decoders")) as server:
        yield server


def ready_decoders(server: Server) -> list[int]:
    """The server's two decoder processes, once both wait for a job."""
    deadline = time.monotonic() + 60
    while len(waiting := waiting_decoders(server.process.pid)) < 2:
        assert time.monotonic() < deadline, "the server's decoders are not ready"
        time.sleep(0.05)
    return waiting


def test_requests_whose_decoders_were_stopped_or_killed_from_outside_are_answered(own_server):
    """Both idle decoders stopped (SIGSTOP), then both killed (SIGKILL, as by the OOM killer): the
    next two plain requests each time are computed (they got 422 `decode_too_costly` after 22 s,
    and 422 `undecodable_image (-9)`)."""
    files = pair_files(*stereo_pair())
    answers, seconds = [], []
    with httpx.Client(base_url=own_server.base_url, timeout=60) as http:
        for sent in (signal.SIGSTOP, signal.SIGKILL):
            for decoder in ready_decoders(own_server):
                os.kill(decoder, sent)
            started_at = time.monotonic()
            answers += [http.post("/disparity", files=files) for _ in range(2)]
            seconds.append(time.monotonic() - started_at)
    assert [answer.status_code for answer in answers] == [200] * 4, [answer.text[:200] for answer in answers]
    assert max(seconds) < 15, seconds  # a ping of 1 s per stopped decoder and a new one's start


def test_deadlines_too_short_to_meet_cost_no_decoder_and_an_abandoned_decode_kills_none(own_server):
    """A flood of `X-Request-Timeout-Ms: 1` is refused before the body is read, and a request whose
    deadline passes while its images decode is answered at once while its decoder finishes: the
    server's decoders are the same processes afterwards (the flood respawned hundreds)."""
    costly = large_progressive_jpeg()
    with httpx.Client(base_url=own_server.base_url, timeout=60) as http:
        before = ready_decoders(own_server)
        short = [
            http.post("/disparity", files=pair_files(*stereo_pair()), headers={"X-Request-Timeout-Ms": "1"})
            for _ in range(20)
        ]
        late = http.post(
            "/disparity",
            files={"left": ("l.jpg", costly, "image/jpeg"), "right": ("r.jpg", costly, "image/jpeg")},
            headers={"X-Request-Timeout-Ms": "300"},
        )
        after = ready_decoders(own_server)
    for answer in short:
        assert (answer.status_code, answer.json()["error"]["code"]) == (503, "deadline_exceeded")
        assert "X-Request-Timeout-Ms is 1 ms" in answer.json()["error"]["message"]
        assert "less than 100 ms" in answer.json()["error"]["message"]
    assert (late.status_code, late.json()["error"]["code"]) == (503, "deadline_exceeded")
    assert late.elapsed.total_seconds() < 1.0  # decoding both images takes over a second
    assert after == before
