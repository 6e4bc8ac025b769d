"""Decoder processes: where untrusted uploads are parsed and decoded, bounded by design.

A multipart body or an image file can be crafted to make its parser or decoder work or allocate
far beyond its size (a TIFF tile bomb, a progressive JPEG of thousands of scans, padding that a
parser walks byte by byte). Header checks refuse the known cases cheaply, but the guarantee is
structural: every such parse and decode (`service.uploads.read_pair`, `decode_pair`) runs in one
of a few worker processes, each with an address-space cap above what it needs to start
(`RLIMIT_AS`) and a CPU-time limit per job (a profiling timer whose signal ends the process; a
wall-clock limit backs it up). A
process that breaches a limit dies or is killed and is replaced, and its request is answered 413
`decode_too_large` or 422 `decode_too_costly`; the server's own memory and event loop never see
the work. A job whose request is abandoned (client gone, deadline passed, drain over) is stopped
the same way.

The parent and the processes talk over pipes in frames of a JSON header and raw buffers (never
pickle: what comes back from a decoder is as untrusted as its input).

    python -m service.decoding MEMORY_BYTES CPU_SECONDS   # one decoder process (started by the pool)
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import os
import signal
import struct
import sys
from collections.abc import Awaitable, Callable
from dataclasses import asdict, dataclass
from typing import Any, BinaryIO

import numpy as np

from service.images import ImageHeader
from service.uploads import ImageLimits, Upload, UploadError, check_headers, decode_pair, read_pair

logger = logging.getLogger(__name__)

Stop = Callable[[], Awaitable[Exception]]
"""Resolves, with the exception to raise, when the request a job serves is abandoned."""

_LENGTH = struct.Struct(">I")
_MAX_META_BYTES = 1 << 16
_WALL_FACTOR = 4.0  # a job may take this many times its CPU limit in wall time (a busy machine)
_WALL_MARGIN_S = 2.0
_EXIT_WAIT_S = 5.0  # how long a process that broke off its answer gets to end before it is killed
_OUT_OF_MEMORY = 3  # exit status of a decoder process that ran out of its memory


@dataclass(frozen=True)
class DecoderLimits:
    """workers: decoder processes; memory_bytes: address space each may add to what it has after
    start-up; cpu_seconds: CPU time one job may use."""

    workers: int
    memory_bytes: int
    cpu_seconds: float

    @property
    def wall_seconds(self) -> float:
        return self.cpu_seconds * _WALL_FACTOR + _WALL_MARGIN_S


class DecoderPool:
    """`workers` decoder processes; a job waits for a free one. `start()` and `close()` run on the
    event loop that uses the pool."""

    def __init__(self, limits: DecoderLimits) -> None:
        self.limits = limits
        self._idle: asyncio.Queue[asyncio.subprocess.Process] = asyncio.Queue()
        self._processes: set[asyncio.subprocess.Process] = set()
        self._spawning: set[asyncio.Task[None]] = set()
        self._closed = False
        self.restarts = 0  # processes replaced after a breach or an abandoned job

    async def start(self) -> None:
        for _ in range(self.limits.workers):
            self._spawn()

    async def close(self) -> None:
        self._closed = True
        for task in list(self._spawning):
            task.cancel()
        await asyncio.gather(*self._spawning, return_exceptions=True)
        for process in list(self._processes):
            await self._kill(process)

    async def read_pair(self, body: bytes, content_type: str, limits: ImageLimits, stop: Stop) -> Upload:
        """`service.uploads.read_pair` in a decoder process."""
        meta, buffers = await self._call(
            {"job": "read_pair", "content_type": content_type, "limits": asdict(limits)}, [body], stop
        )
        rig = meta.get("rig")
        if len(buffers) != 2 or not isinstance(rig, str | None):
            raise RuntimeError("decoder process answered read_pair with a malformed frame")
        return Upload(buffers[0], buffers[1], _header(meta), rig)

    async def check_headers(self, left: bytes, right: bytes, limits: ImageLimits, stop: Stop) -> ImageHeader:
        """`service.uploads.check_headers` in a decoder process: two image files (a stream's
        frame), checked from their headers; the left one's header."""
        meta, _ = await self._call({"job": "check_headers", "limits": asdict(limits)}, [left, right], stop)
        return _header(meta)

    async def decode_pair(
        self, left: bytes, right: bytes, header: ImageHeader, stop: Stop
    ) -> tuple[np.ndarray, np.ndarray]:
        """`service.uploads.decode_pair` in a decoder process: uint8 RGB images of `header`'s size."""
        _, buffers = await self._call({"job": "decode_pair"}, [left, right], stop)
        shape = (header.height, header.width, 3)
        if len(buffers) != 2 or any(len(b) != math.prod(shape) for b in buffers):
            raise RuntimeError("decoder process answered decode_pair with a malformed frame")
        left_image, right_image = (np.frombuffer(b, dtype=np.uint8).reshape(shape) for b in buffers)
        return left_image, right_image

    async def _call(self, meta: dict[str, Any], buffers: list[bytes], stop: Stop) -> tuple[dict[str, Any], list[bytes]]:
        if self._closed:
            raise RuntimeError("the decoder pool is closed")
        stopped = asyncio.ensure_future(stop())
        try:
            process = await _unless(stopped, self._idle.get())
            try:
                reply = await _unless(
                    stopped, asyncio.wait_for(self._exchange(process, meta, buffers), self.limits.wall_seconds)
                )
            except BaseException as exc:
                ended = isinstance(exc, asyncio.IncompleteReadError | ConnectionError)  # the process ended itself
                await self._replace(process, ended)
                if ended:
                    raise self._breach(process.returncode) from None
                if isinstance(exc, TimeoutError):
                    raise self._too_costly() from None
                raise
            self._idle.put_nowait(process)
        finally:
            stopped.cancel()
        reply_meta, reply_buffers = reply
        if not reply_meta.get("ok"):
            raise UploadError(int(reply_meta["status"]), str(reply_meta["code"]), str(reply_meta["message"]))
        return reply_meta, reply_buffers

    async def _exchange(
        self, process: asyncio.subprocess.Process, meta: dict[str, Any], buffers: list[bytes]
    ) -> tuple[dict[str, Any], list[bytes]]:
        assert process.stdin is not None and process.stdout is not None
        for part in _frame(meta, buffers):
            process.stdin.write(part)
        await process.stdin.drain()
        (meta_size,) = _LENGTH.unpack(await process.stdout.readexactly(_LENGTH.size))
        if meta_size > _MAX_META_BYTES:
            raise RuntimeError("decoder process sent an oversized frame header")
        reply = json.loads(await process.stdout.readexactly(meta_size))
        sizes = reply.get("sizes", [])
        return reply, [await process.stdout.readexactly(int(size)) for size in sizes]

    def _too_costly(self) -> UploadError:
        return UploadError(
            422,
            "decode_too_costly",
            f"reading these images took more than {self.limits.cpu_seconds:g} s of CPU; "
            "re-encode them plainly (baseline JPEG, PNG) and try again",
        )

    def _breach(self, returncode: int | None) -> UploadError:
        """The answer for a job whose process ended with `returncode` before answering."""
        if returncode == -signal.SIGPROF:
            return self._too_costly()
        if returncode == _OUT_OF_MEMORY:
            return UploadError(
                413,
                "decode_too_large",
                f"reading these images needs more than the {self.limits.memory_bytes >> 20} MiB the server "
                "allows per upload; send smaller or plainer images",
            )
        return UploadError(422, "undecodable_image", f"the decoder failed on these images (status {returncode})")

    async def _replace(self, process: asyncio.subprocess.Process, ended: bool) -> None:
        """Retire `process` and start another. `ended`: it is ending by itself (a breach), and its
        exit status says why; killing it then could reap it before the status is read."""
        if ended:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(process.wait(), _EXIT_WAIT_S)
        await self._kill(process)
        self.restarts += 1
        logger.warning("decoder process replaced", extra={"returncode": process.returncode})
        if not self._closed:
            self._spawn()

    async def _kill(self, process: asyncio.subprocess.Process) -> None:
        self._processes.discard(process)
        if process.returncode is None:  # (killing an ended process would reap it, and lose its status)
            with contextlib.suppress(ProcessLookupError):
                process.kill()
        await process.wait()

    def _spawn(self) -> None:
        task = asyncio.create_task(self._start_process())
        self._spawning.add(task)
        task.add_done_callback(self._spawning.discard)

    async def _start_process(self) -> None:
        try:
            process = await self._launch()
        except OSError:
            logger.exception("could not start a decoder process")
            return
        self._processes.add(process)
        self._idle.put_nowait(process)

    async def _launch(self) -> asyncio.subprocess.Process:
        return await asyncio.create_subprocess_exec(
            sys.executable,
            "-m",
            "service.decoding",
            str(self.limits.memory_bytes),
            str(self.limits.cpu_seconds),
            stdin=asyncio.subprocess.PIPE,
            stdout=asyncio.subprocess.PIPE,
            limit=1 << 20,
        )


def _header(meta: dict[str, Any]) -> ImageHeader:
    """The image header a decoder process answered with."""
    header = meta.get("header")
    if not isinstance(header, dict):
        raise RuntimeError("decoder process answered without an image header")
    return ImageHeader(str(header["format"]), int(header["width"]), int(header["height"]))


async def _unless(stopped: asyncio.Future[Exception], work: Awaitable[Any]) -> Any:
    """The result of `work`, unless `stopped` resolves first: then `work` is cancelled and the
    exception `stopped` resolved with is raised."""
    task = asyncio.ensure_future(work)
    await asyncio.wait({task, stopped}, return_when=asyncio.FIRST_COMPLETED)
    if task.done():
        return task.result()
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task
    raise stopped.result()


def _frame(meta: dict[str, Any], buffers: list[bytes]) -> list[bytes]:
    header = json.dumps({**meta, "sizes": [len(b) for b in buffers]}).encode()
    return [_LENGTH.pack(len(header)), header, *buffers]


def _read_frame(stream: BinaryIO) -> tuple[dict[str, Any], list[bytes]] | None:
    """The next frame on a blocking stream (None at its end)."""
    prefix = stream.read(_LENGTH.size)
    if len(prefix) < _LENGTH.size:
        return None
    (meta_size,) = _LENGTH.unpack(prefix)
    meta = json.loads(stream.read(meta_size))
    return meta, [stream.read(int(size)) for size in meta["sizes"]]


def _run_job(meta: dict[str, Any], buffers: list[bytes]) -> tuple[dict[str, Any], list[bytes]]:
    if meta["job"] == "read_pair":
        upload = read_pair(buffers[0], meta["content_type"], ImageLimits(**meta["limits"]))
        return {"ok": True, "header": asdict(upload.header), "rig": upload.rig}, [upload.left, upload.right]
    if meta["job"] == "check_headers":
        header = check_headers(ImageLimits(**meta["limits"]), buffers[0], buffers[1])
        return {"ok": True, "header": asdict(header)}, []
    if meta["job"] == "decode_pair":
        images = decode_pair(buffers[0], buffers[1])
        return {"ok": True}, [np.ascontiguousarray(image).tobytes() for image in images]
    raise ValueError(f"unknown job {meta['job']!r}")


def _serve(memory_bytes: int, cpu_seconds: float) -> None:
    """A decoder process: jobs in on stdin, answers out on stdout, until stdin closes."""
    import resource

    import cv2

    cv2.setNumThreads(1)
    signal.signal(signal.SIGPROF, signal.SIG_DFL)
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))  # a breach leaves no core file
    _, hard = resource.getrlimit(resource.RLIMIT_AS)
    resource.setrlimit(resource.RLIMIT_AS, (_address_space() + memory_bytes, hard))
    stdin, stdout = sys.stdin.buffer, sys.stdout.buffer
    try:
        while (frame := _read_frame(stdin)) is not None:
            signal.setitimer(signal.ITIMER_PROF, cpu_seconds)  # SIGPROF (fatal) after that much CPU time
            try:
                meta, buffers = _run_job(*frame)
            except UploadError as exc:
                meta, buffers = {"ok": False, "status": exc.status, "code": exc.code, "message": exc.message}, []
            finally:
                signal.setitimer(signal.ITIMER_PROF, 0)
            for part in _frame(meta, buffers):
                stdout.write(part)
            stdout.flush()
    except MemoryError:
        os._exit(_OUT_OF_MEMORY)  # the parent answers 413 decode_too_large and starts another process


def _address_space() -> int:
    """This process's virtual memory size in bytes."""
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")


if __name__ == "__main__":
    _serve(int(sys.argv[1]), float(sys.argv[2]))
