"""Dynamic batching: requests queue per model and run, one batch at a time, on one inference thread.

The batcher knows nothing of what it computes: a request is a key (`service.batching.policy.BatchKey`:
requests with equal keys may share a batch) and a payload; an adapter says what a request costs
(`work`) and computes a batch of payloads on the inference thread (`compute`). The stereo adapter is
`service.batching.stereo.StereoBatches` (a batch holds pairs of one model, one set of inference
options and one input shape). Whenever the inference thread is free, `service.batching.policy.choose_batch`
picks the next batch from the queued requests and those still being received or decoded. Before
a batch runs, requests whose client has gone, whose deadline has passed or cannot be met
(estimated from the measured compute time per unit of work, `service.batching.policy.ComputeTimes`) are
dropped. An exception in the network fails only the batch it happened in.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
import uuid
from collections import deque
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from concurrent.futures import Executor
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from typing import Generic, Protocol, TypeVar

from crestereo_pp.service.api.metrics import Metrics
from crestereo_pp.service.batching.policy import BatchKey, BatchLimits, ComputeTimes, choose_batch
from crestereo_pp.service.settings import Settings

logger = logging.getLogger(__name__)


class BatchingError(Exception):
    """A request the batcher could not compute."""


class QueueFull(BatchingError):
    def __init__(self, retry_after_s: int) -> None:
        super().__init__(f"queue full; retry in {retry_after_s} s")
        self.retry_after_s = retry_after_s


class Draining(BatchingError):
    """The server is shutting down and takes no more work (or ran out of drain time)."""


class DeadlineExceeded(BatchingError):
    """The request's deadline passed, or would pass before its batch could finish; a retry
    likely finds the queue worked off after `retry_after_s` seconds."""

    def __init__(self, message: str, retry_after_s: int) -> None:
        super().__init__(message)
        self.retry_after_s = retry_after_s


class ClientDisconnected(BatchingError):
    """The client went away before the request was computed."""


class InferenceFailed(BatchingError):
    def __init__(self, error_id: str) -> None:
        super().__init__(f"inference failed; logged as error id {error_id}")
        self.error_id = error_id


KeyT = TypeVar("KeyT", bound=BatchKey)
PayloadT = TypeVar("PayloadT")
OutputT = TypeVar("OutputT")


KeyIn = TypeVar("KeyIn", bound=BatchKey, contravariant=True)
PayloadIn = TypeVar("PayloadIn", contravariant=True)
OutputOut = TypeVar("OutputOut", covariant=True)


class Adapter(Protocol[KeyIn, PayloadIn, OutputOut]):
    """What the batcher computes: one queue per model of `models`; `work(key)`, the units of
    compute of one request of `key` (the compute-time estimates count in them); `compute(key,
    payloads)`, the outputs of a batch, in order, on the inference thread."""

    @property
    def models(self) -> list[str]: ...

    def work(self, key: KeyIn) -> float: ...

    def compute(self, key: KeyIn, payloads: Sequence[PayloadIn]) -> Sequence[OutputOut]: ...


@dataclass(frozen=True)
class JobResult(Generic[OutputT]):
    """A computed request: its output and how it was computed."""

    output: OutputT
    batch_size: int  # requests in its batch
    queue_seconds: float  # from queueing until its batch started
    compute_seconds: float  # of the whole batch


@dataclass(eq=False)
class _Job(Generic[KeyT, PayloadT, OutputT]):
    key: KeyT
    payload: PayloadT
    deadline: float | None  # time.monotonic() by which the answer is due
    is_disconnected: Callable[[], Awaitable[bool]]
    request_id: str | None
    enqueued_at: float = field(default_factory=time.monotonic)
    dispatched: bool = False  # its batch has started; its admission no longer counts it
    future: asyncio.Future[JobResult[OutputT]] = field(
        default_factory=lambda: asyncio.get_running_loop().create_future()
    )


class Admission(Generic[KeyT, PayloadT, OutputT]):
    """A request's place in its model's queue, from before decoding until its batch starts."""

    def __init__(self, batcher: Batcher[KeyT, PayloadT, OutputT], model: str) -> None:
        self._batcher = batcher
        self.model = model
        self.job: _Job[KeyT, PayloadT, OutputT] | None = None

    async def run(
        self,
        key: KeyT,
        payload: PayloadT,
        *,
        deadline: float | None,
        is_disconnected: Callable[[], Awaitable[bool]],
        request_id: str | None = None,
    ) -> JobResult[OutputT]:
        """Queue a request of `key` (of this admission's model) and wait for its result."""
        if key.model != self.model:
            raise ValueError(f"a request of model {key.model!r} in an admission for {self.model!r}")
        job: _Job[KeyT, PayloadT, OutputT] = _Job(key, payload, deadline, is_disconnected, request_id)
        if deadline is not None and deadline <= job.enqueued_at:
            raise DeadlineExceeded(
                "deadline passed before the request was queued", self._batcher.retry_after(self.model)
            )
        self.job = job
        self._batcher.enqueue(job)
        timeout = None if deadline is None else deadline - job.enqueued_at
        try:
            return await asyncio.wait_for(asyncio.shield(job.future), timeout)
        except TimeoutError:
            raise DeadlineExceeded(
                "deadline passed while waiting for the result", self._batcher.retry_after(self.model)
            ) from None


class Batcher(Generic[KeyT, PayloadT, OutputT]):
    """Per-model queues, the batch scheduler and the inference thread that computes batches."""

    def __init__(
        self,
        settings: Settings,
        adapter: Adapter[KeyT, PayloadT, OutputT],
        executor: Executor,
        metrics: Metrics,
    ) -> None:
        self._settings = settings
        self._adapter = adapter
        self._executor = executor
        self._metrics = metrics
        models = adapter.models
        self._queues: dict[str, deque[_Job[KeyT, PayloadT, OutputT]]] = {name: deque() for name in models}
        self._pending: dict[str, int] = dict.fromkeys(models, 0)
        self._running: list[_Job[KeyT, PayloadT, OutputT]] = []
        self._running_since = 0.0
        self._limits = BatchLimits(settings.max_batch_size, settings.max_batch_pixels, settings.max_wait_ms / 1000)
        self._times = ComputeTimes()
        self._changed = asyncio.Event()
        self._draining = False
        self._abandoned: BatchingError | None = None  # set by `abandon`: the answer to all work from then on
        self._task: asyncio.Task[None] | None = None
        for name in models:
            metrics.queue_depth.labels(model=name).set(0)

    def start(self) -> None:
        self._task = asyncio.create_task(self._schedule(), name="batch-scheduler")

    async def close(self) -> None:
        """Stop scheduling; whatever is queued or running gets `Draining`."""
        self._draining = True
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
        self._fail([*self._running, *self._take_queued()], Draining("server stopped"))

    @property
    def is_running(self) -> bool:
        """The scheduler is alive (False after `close()` or if it crashed)."""
        return self._task is not None and not self._task.done()

    def begin_drain(self) -> None:
        """Admit nothing more; what is already admitted still runs."""
        self._draining = True

    def abandon(self, error: BatchingError) -> None:
        """Answer every queued and computing request with `error`, and every request queued from
        now on (one still being decoded now, say); a computing batch runs on, but its result is
        dropped."""
        self._abandoned = error
        self._fail([*self._running, *self._take_queued()], error)

    def _take_queued(self) -> list[_Job[KeyT, PayloadT, OutputT]]:
        jobs = [job for queue in self._queues.values() for job in queue]
        for queue in self._queues.values():
            queue.clear()
        return jobs

    def queue_depths(self) -> dict[str, int]:
        """Per model: requests admitted and not yet computing."""
        return dict(self._pending)

    def work_ahead_s(self, model: str) -> float | None:
        """Estimated seconds of compute ahead of a request of `model` admitted now. One inference
        thread computes every model's batches, so this is what remains of the running batch,
        whichever model's, plus every request of every model admitted and not yet computing
        (queued ones at their padded size, those still being received or decoded at their model's
        mean size), each at its model's measured seconds per unit of work; a model not measured
        yet adds nothing. None before any batch of `model` itself has been measured."""
        return None if self._times.get(model) is None else self._work_ahead_s()

    def _work_ahead_s(self) -> float:
        ahead = 0.0
        for model, queued in self._queues.items():
            times = self._times.get(model)
            if times is not None:
                decoding = self._pending[model] - len(queued)
                ahead += times.seconds(sum(self.work(job.key) for job in queued) + decoding * times.work_per_request)
        running = self._times.get(self._running[0].key.model) if self._running else None
        if running is not None:
            batch_work = len(self._running) * self.work(self._running[0].key)
            ahead += max(0.0, running.seconds(batch_work) - (time.monotonic() - self._running_since))
        return ahead

    def work(self, key: KeyT) -> float:
        """Units of compute of one request of `key` (the adapter's count)."""
        return self._adapter.work(key)

    def retry_after(self, model: str) -> int:
        """Seconds after which a retry likely finds the model's queue worked off: the work ahead
        (`work_ahead_s`), or 1 s per admitted request before anything has been measured."""
        ahead = self.work_ahead_s(model)
        return max(1, math.ceil(self._pending[model] + 1 if ahead is None else ahead))

    @asynccontextmanager
    async def admit(
        self, model: str, key: KeyT | None = None, deadline: float | None = None
    ) -> AsyncIterator[Admission[KeyT, PayloadT, OutputT]]:
        """Reserve a queue place for `model` before the request is decoded (raises `QueueFull`,
        `Draining`, or `DeadlineExceeded` when the work ahead plus this request's, of `key`,
        cannot finish by `deadline`); the place is given back when the batch starts or the
        request ends."""
        if self._draining:
            raise Draining("server is shutting down")
        if self._pending[model] >= self._settings.max_queue:
            raise QueueFull(self.retry_after(model))
        times = self._times.get(model)
        if deadline is not None and key is not None and times is not None:
            finish = time.monotonic() + self._work_ahead_s() + times.seconds(self.work(key))
            if finish > deadline:
                raise DeadlineExceeded(
                    f"deadline cannot be met: about {finish - time.monotonic():.1f} s of compute would be needed",
                    self.retry_after(model),
                )
        admission: Admission[KeyT, PayloadT, OutputT] = Admission(self, model)
        self._set_pending(model, +1)
        try:
            yield admission
        finally:
            job = admission.job
            if job is None or not job.dispatched:
                self._set_pending(model, -1)
            if job is not None and job in self._queues[model]:
                self._queues[model].remove(job)
                job.future.cancel()
            self._changed.set()

    def enqueue(self, job: _Job[KeyT, PayloadT, OutputT]) -> None:
        if self._abandoned is not None:
            raise self._abandoned
        self._queues[job.key.model].append(job)
        self._changed.set()

    # --- scheduler --------------------------------------------------------------------------

    async def _schedule(self) -> None:
        try:
            while True:
                batch = await self._next_batch()
                await self._execute(batch)
        except Exception:  # a bug: liveness turns 503 (see `is_running`) so the process restarts
            logger.exception("batch scheduler stopped")
            raise

    async def _next_batch(self) -> list[_Job[KeyT, PayloadT, OutputT]]:
        while True:
            self._changed.clear()
            queued = [job for queue in self._queues.values() for job in queue]
            incoming = sum(self._pending.values()) - len(queued)
            batch, wait_s = choose_batch(queued, incoming, time.monotonic(), self._limits)
            if batch:
                if await self._drop_unservable(batch):
                    continue  # the batch changed: choose again, with the requests still here
                return batch
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._changed.wait(), wait_s)

    async def _drop_unservable(self, batch: list[_Job[KeyT, PayloadT, OutputT]]) -> bool:
        """Drop requests of `batch` whose client left or whose deadline cannot be met; True when
        the batch is no longer intact."""
        changed = False
        for job in batch:
            if await job.is_disconnected():
                self._drop(job, ClientDisconnected("client disconnected before compute"))
                changed = True
        times = self._times.get(batch[0].key.model)
        estimate = 0.0 if times is None else times.seconds(len(batch) * self.work(batch[0].key))
        finish = time.monotonic() + estimate
        for job in batch:
            if job.deadline is not None and finish > job.deadline and not job.future.done():
                self._drop(job, DeadlineExceeded("deadline cannot be met", self.retry_after(job.key.model)))
                changed = True
        # Requests can also leave while the disconnect checks above await.
        return changed or any(job.future.done() for job in batch)

    def _drop(self, job: _Job[KeyT, PayloadT, OutputT], error: BatchingError) -> None:
        queue = self._queues[job.key.model]
        if job in queue:
            queue.remove(job)
        self._fail([job], error)

    async def _execute(self, batch: list[_Job[KeyT, PayloadT, OutputT]]) -> None:
        key = batch[0].key
        started = time.monotonic()
        for job in batch:
            self._queues[key.model].remove(job)
            job.dispatched = True
            self._metrics.queue_wait.labels(model=key.model).observe(started - job.enqueued_at)
        self._set_pending(key.model, -len(batch))  # their admissions no longer count them
        self._running, self._running_since = batch, started
        try:
            outputs = await asyncio.get_running_loop().run_in_executor(
                self._executor,
                self._adapter.compute,
                key,
                [job.payload for job in batch],
            )
        except Exception as exc:  # any failure of the network fails this batch only
            error_id = uuid.uuid4().hex[:12]
            logger.error(
                "inference failed",
                exc_info=exc,
                extra={
                    "error_id": error_id,
                    "model": key.model,
                    "batch_size": len(batch),
                    "request_ids": [job.request_id for job in batch],
                },
            )
            self._fail(batch, InferenceFailed(error_id))
            return
        finally:
            self._running = []
        compute = time.monotonic() - started
        self._metrics.compute.labels(model=key.model).observe(compute)
        self._metrics.batch_size.labels(model=key.model).observe(len(batch))
        self._times.record(key.model, self.work(key), len(batch), compute)
        for job, output in zip(batch, outputs, strict=True):
            if not job.future.done():
                job.future.set_result(JobResult(output, len(batch), started - job.enqueued_at, compute))

    def _set_pending(self, model: str, delta: int) -> None:
        self._pending[model] += delta
        self._metrics.queue_depth.labels(model=model).set(self._pending[model])

    @staticmethod
    def _fail(jobs: Sequence[_Job[KeyT, PayloadT, OutputT]], error: BatchingError) -> None:
        for job in jobs:
            if not job.future.done():
                job.future.set_exception(error)
