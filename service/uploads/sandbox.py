"""Decoder processes: where untrusted uploads are parsed and decoded, bounded by design.

A multipart body or an image file can be crafted to make its parser or decoder work or allocate
far beyond its size (a TIFF tile bomb, a progressive JPEG of thousands of scans, padding that a
parser walks byte by byte). Header checks refuse the known cases cheaply, but the guarantee is
structural: every such parse and decode (`service.uploads.read_pair`, `decode_pair`) runs in one
of a few decoder processes, each with an address-space cap above what it needs to start
(`RLIMIT_AS`) and a CPU-time limit per job (a profiling timer whose signal ends the process; a
wall-clock limit backs it up). A
process that breaches a limit dies or is killed and is replaced, and its request is answered 413
`decode_too_large` or 422 `decode_too_costly`; the server's own memory and event loop never see
the work. A job whose request is abandoned (client gone, deadline passed, drain over) is answered
at once and left to finish within those limits, its answer discarded: a decoder is never killed
for it.

A process can also be lost from outside: killed (the OOM killer, an operator) or stopped. That is
no upload's fault. Each job goes to a process that has just answered a ping (one lost while idle
is replaced, and the next tried); a process lost during a job is replaced and the job run once
more on another, and only a second such loss is put down to the upload.

The parent and the processes talk over pipes in frames of a JSON header and raw buffers (never
pickle: what comes back from a decoder is as untrusted as its input).

    python -m crestereo_pp.service.uploads.sandbox MEMORY_BYTES CPU_SECONDS  # one decoder process (the pool starts it)
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

from crestereo_pp.service.uploads.images import ImageHeader
from crestereo_pp.service.uploads.multipart import (
    ImageLimits,
    Upload,
    UploadError,
    check_headers,
    decode_pair,
    read_pair,
)

logger = logging.getLogger(__name__)

Stop = Callable[[], Awaitable[Exception]]
"""Resolves, with the exception to raise, when the request a job serves is abandoned."""

_LENGTH = struct.Struct(">I")
_MAX_META_BYTES = 1 << 16
_WALL_FACTOR = 4.0  # a job may take this many times its CPU limit in wall time (a busy machine)
_WALL_MARGIN_S = 2.0
_EXIT_WAIT_S = 5.0  # how long a process that broke off its answer gets to end before it is killed
_OUT_OF_MEMORY = 3  # exit status of a decoder process that ran out of its memory
_STDERR_LINES_PER_S = 20  # lines of a decoder's stderr logged a second at most; the others are counted


@dataclass(frozen=True)
class DecoderLimits:
    """processes: decoder processes; memory_bytes: address space each may add to what it has after
    start-up; cpu_seconds: CPU time one job may use."""

    processes: int
    memory_bytes: int
    cpu_seconds: float

    @property
    def wall_seconds(self) -> float:
        return self.cpu_seconds * _WALL_FACTOR + _WALL_MARGIN_S


Reply = tuple[dict[str, Any], list[bytes]]
"""A decoder process's answer to a job: its JSON header and its buffers."""

_PING: dict[str, Any] = {"job": "ping"}
_PING_TIMEOUT_S = 1.0  # an idle process answers a ping within milliseconds; one that does not is lost
_START_TIMEOUT_S = 60.0  # a new process says it is ready (its imports done) within this
_RESTART_DELAY_S = 1.0  # before another try where a process did not start


@dataclass(frozen=True)
class _Lost:
    """A job whose process ended or stalled before answering, not by breaching its limits (it may
    have been killed or stopped from outside); `error`: the answer should that happen twice."""

    error: UploadError


class DecoderPool:
    """`processes` decoder processes; a job waits for a free one. `start()` and `close()` run on the
    event loop that uses the pool."""

    def __init__(self, limits: DecoderLimits) -> None:
        self.limits = limits
        self._idle: asyncio.Queue[asyncio.subprocess.Process] = asyncio.Queue()
        self._processes: set[asyncio.subprocess.Process] = set()
        self._spawning: set[asyncio.Task[None]] = set()
        self._jobs: set[asyncio.Task[Reply | _Lost | None]] = set()  # running, awaited or abandoned
        self._relays: set[asyncio.Task[None]] = set()  # one per process: its stderr into the logs
        self._closed = False
        self.restarts = 0  # processes replaced: after a breach, or lost from outside

    async def start(self) -> None:
        for _ in range(self.limits.processes):
            self._spawn()

    async def close(self) -> None:
        self._closed = True
        for task in list(self._spawning):
            task.cancel()
        await asyncio.gather(*self._spawning, return_exceptions=True)
        for process in list(self._processes):
            await self._kill(process)
        await asyncio.gather(*self._jobs, return_exceptions=True)  # their processes are gone: they end
        await asyncio.gather(*self._relays, return_exceptions=True)  # and their stderr has ended

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

    async def _call(self, meta: dict[str, Any], buffers: list[bytes], stop: Stop) -> Reply:
        """The job's answer; a job whose process was lost runs once more on another."""
        if self._closed:
            raise RuntimeError("the decoder pool is closed")
        stopped = asyncio.ensure_future(stop())
        try:
            outcome = await self._attempt(meta, buffers, stopped)
            if isinstance(outcome, _Lost):
                logger.warning("decoder process lost during a job; running it on another", extra={"job": meta["job"]})
                outcome = await self._attempt(meta, buffers, stopped)
        finally:
            stopped.cancel()
        if isinstance(outcome, _Lost):
            raise outcome.error
        reply_meta, reply_buffers = outcome
        if not reply_meta.get("ok"):
            raise UploadError(int(reply_meta["status"]), str(reply_meta["code"]), str(reply_meta["message"]))
        return reply_meta, reply_buffers

    async def _attempt(
        self, meta: dict[str, Any], buffers: list[bytes], stopped: asyncio.Future[Exception]
    ) -> Reply | _Lost:
        """One run of the job, on the next idle process that answers a ping; `stopped`'s exception
        once the request is abandoned (the job runs on, and its answer is discarded)."""
        while True:
            process = await unless(stopped, self._idle.get())
            job = asyncio.ensure_future(self._run(process, meta, buffers))
            self._jobs.add(job)
            job.add_done_callback(self._job_done)
            outcome: Reply | _Lost | None = await unless(stopped, asyncio.shield(job))
            if outcome is not None:
                return outcome

    def _job_done(self, job: asyncio.Task[Reply | _Lost | None]) -> None:
        self._jobs.discard(job)
        if not job.cancelled():
            job.exception()  # seen, also when its request was abandoned and nobody awaits it

    async def _run(
        self, process: asyncio.subprocess.Process, meta: dict[str, Any], buffers: list[bytes]
    ) -> Reply | _Lost | None:
        """The job on `process` once it has answered a ping; the process then goes back to idle, or
        is replaced where it failed. None: it did not answer the ping (lost while idle); `_Lost`:
        it ended or stalled during the job, not by its limits; UploadError (raised): it breached them."""
        try:
            await asyncio.wait_for(self._exchange(process, _PING, []), _PING_TIMEOUT_S)
        except Exception:
            await self._replace(process, ended=False)
            return None
        try:
            reply = await asyncio.wait_for(self._exchange(process, meta, buffers), self.limits.wall_seconds)
        except (asyncio.IncompleteReadError, ConnectionError):  # the process ended
            await self._replace(process, ended=True)
            error = self._breach(process.returncode)
            if _maybe_from_outside(process.returncode):
                return _Lost(error)
            raise error from None
        except TimeoutError:  # stopped, or starved of CPU: its CPU timer ends a job that uses too much
            await self._replace(process, ended=False)
            return _Lost(self._too_costly())
        except BaseException:  # a malformed answer, or the pool is closing
            await self._replace(process, ended=False)
            raise
        self._idle.put_nowait(process)
        return reply

    async def _exchange(self, process: asyncio.subprocess.Process, meta: dict[str, Any], buffers: list[bytes]) -> Reply:
        assert process.stdin is not None
        for part in _frame(meta, buffers):
            process.stdin.write(part)
        await process.stdin.drain()
        return await _read_reply(process)

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
        if self._closed:
            return
        self.restarts += 1
        logger.warning("decoder process replaced", extra={"returncode": process.returncode})
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
        """A new process, idle once it says it is ready; where it does not start (killed while it
        starts, say), another a second later."""
        try:
            process = await self._launch()
        except OSError:
            logger.exception("could not start a decoder process")
        else:
            self._processes.add(process)
            try:
                await asyncio.wait_for(_read_reply(process), _START_TIMEOUT_S)
            except Exception:
                logger.exception("a decoder process did not start", extra={"returncode": process.returncode})
                await self._kill(process)
            else:
                self._idle.put_nowait(process)
                return
        await asyncio.sleep(_RESTART_DELAY_S)
        if not self._closed:
            self._spawn()

    async def _launch(self) -> asyncio.subprocess.Process:
        process = await asyncio.create_subprocess_exec(
            sys.executable,
            "-m",
            "crestereo_pp.service.uploads.sandbox",
            str(self.limits.memory_bytes),
            str(self.limits.cpu_seconds),
            stdin=asyncio.subprocess.PIPE,
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE,
            limit=1 << 20,
        )
        relay = asyncio.create_task(_log_stderr(process))
        self._relays.add(relay)
        relay.add_done_callback(self._relays.discard)
        return process


async def _log_stderr(process: asyncio.subprocess.Process) -> None:
    """Log each line `process` writes on stderr (the image decoders' warnings, such as "libpng
    warning: IDAT: Too much image data", or a traceback) as a warning, so that the service's logs
    stay JSON; at most _STDERR_LINES_PER_S a second, those over it counted in the next one logged.
    Ends when the process's stderr closes."""
    assert process.stderr is not None
    window, logged, dropped = -1, 0, 0
    while True:
        try:
            line = await process.stderr.readline()
        except ValueError:  # a line over the reader's limit, dropped by it
            line = b"(a line over 1 MiB)\n"
        if not line:
            return
        second = int(asyncio.get_running_loop().time())
        if second != window:
            window, logged = second, 0
        if logged >= _STDERR_LINES_PER_S:
            dropped += 1
            continue
        logged += 1
        text = line.decode(errors="replace").rstrip()
        logger.warning("decoder process wrote: %s", text, extra={"pid": process.pid, "lines_dropped": dropped})
        dropped = 0


def _maybe_from_outside(returncode: int | None) -> bool:
    """Whether a process that ended with `returncode` may have been ended from outside (SIGKILL
    from the OOM killer, say) rather than by its upload: a signal other than its own CPU timer.
    An exit status is the process's own (out of memory, an error)."""
    return returncode is None or (returncode < 0 and returncode != -signal.SIGPROF)


async def _read_reply(process: asyncio.subprocess.Process) -> Reply:
    """The next frame `process` sends."""
    assert process.stdout is not None
    (meta_size,) = _LENGTH.unpack(await process.stdout.readexactly(_LENGTH.size))
    if meta_size > _MAX_META_BYTES:
        raise RuntimeError("decoder process sent an oversized frame header")
    reply = json.loads(await process.stdout.readexactly(meta_size))
    sizes = reply.get("sizes", [])
    return reply, [await process.stdout.readexactly(int(size)) for size in sizes]


def _header(meta: dict[str, Any]) -> ImageHeader:
    """The image header a decoder process answered with."""
    header = meta.get("header")
    if not isinstance(header, dict):
        raise RuntimeError("decoder process answered without an image header")
    return ImageHeader(str(header["format"]), int(header["width"]), int(header["height"]))


async def unless(stopped: asyncio.Future[Exception], work: Awaitable[Any]) -> Any:
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


def _write_frame(stream: BinaryIO, meta: dict[str, Any], buffers: list[bytes]) -> None:
    for part in _frame(meta, buffers):
        stream.write(part)
    stream.flush()


def _read_frame(stream: BinaryIO) -> tuple[dict[str, Any], list[bytes]] | None:
    """The next frame on a blocking stream (None at its end)."""
    prefix = stream.read(_LENGTH.size)
    if len(prefix) < _LENGTH.size:
        return None
    (meta_size,) = _LENGTH.unpack(prefix)
    meta = json.loads(stream.read(meta_size))
    return meta, [stream.read(int(size)) for size in meta["sizes"]]


def _run_job(meta: dict[str, Any], buffers: list[bytes]) -> Reply:
    if meta["job"] == "ping":
        return {"ok": True}, []
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
    _write_frame(stdout, {"ok": True}, [])  # ready
    try:
        while (frame := _read_frame(stdin)) is not None:
            signal.setitimer(signal.ITIMER_PROF, cpu_seconds)  # SIGPROF (fatal) after that much CPU time
            try:
                meta, buffers = _run_job(*frame)
            except UploadError as exc:
                meta, buffers = {"ok": False, "status": exc.status, "code": exc.code, "message": exc.message}, []
            finally:
                signal.setitimer(signal.ITIMER_PROF, 0)
            _write_frame(stdout, meta, buffers)
    except MemoryError:
        os._exit(_OUT_OF_MEMORY)  # the parent answers 413 decode_too_large and starts another process


def _address_space() -> int:
    """This process's virtual memory size in bytes."""
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")


if __name__ == "__main__":
    _serve(int(sys.argv[1]), float(sys.argv[2]))
