"""The batch scheduler's decisions, apart from its queues and the event loop (`service.batching.batcher`),
for requests of any kind: which batch runs next (`choose_batch`) and the measured compute times
that estimate the work ahead (`ComputeTimes`). Which requests may share a batch is their key's
business (`BatchKey`; the stereo one is `service.batching.stereo.StereoKey`)."""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass
from typing import Protocol, TypeVar


class BatchKey(Hashable, Protocol):
    """What the batcher knows of a request's kind: requests with equal keys may share a batch,
    `model` names the queue (and the compute-time statistics) they go to, `pixels` the size
    of one request (the batch pixel limit)."""

    @property
    def model(self) -> str: ...

    @property
    def pixels(self) -> int: ...


@dataclass(frozen=True)
class BatchLimits:
    """How large a batch may be and how long a partial one may wait (from the settings)."""

    max_batch_size: int
    max_batch_pixels: int  # padded pixels of all its requests together
    max_wait_s: float

    def capacity(self, key: BatchKey) -> int:
        """Requests of `key` in a full batch; at least 1, so a larger image still runs, alone."""
        return max(1, min(self.max_batch_size, self.max_batch_pixels // key.pixels))


class Queued(Protocol):
    """A queued request, as far as the choice of the next batch looks at it."""

    @property
    def key(self) -> BatchKey: ...

    @property
    def enqueued_at(self) -> float: ...  # time.monotonic() when it was queued


QueuedT = TypeVar("QueuedT", bound=Queued)


def choose_batch(
    queued: Sequence[QueuedT], incoming: int, now: float, limits: BatchLimits
) -> tuple[list[QueuedT], float | None]:
    """The batch to run now, or none and how long to wait at most (None: until something changes).

    queued: every queued request, of every model; incoming: requests admitted but not queued yet
    (still being received or decoded); now: `time.monotonic()`. Requests group by key, oldest
    group first, and a batch takes the oldest requests of its group up to `limits.capacity`.
    The rules, in order:
    1. the oldest group if its oldest request has waited `max_wait_s`;
    2. else the oldest group that is full;
    3. else, when nothing is incoming, the oldest group at once (an idle server runs a lone
       request immediately);
    4. else nothing yet: wait for more, at most until rule 1 applies.
    """
    groups: dict[BatchKey, list[QueuedT]] = {}
    for request in sorted(queued, key=lambda request: request.enqueued_at):
        groups.setdefault(request.key, []).append(request)
    if not groups:
        return [], None
    candidates: list[tuple[list[QueuedT], bool]] = []  # (batch, is full), oldest first
    for key, requests in groups.items():
        capacity = limits.capacity(key)
        candidates.append((requests[:capacity], len(requests) >= capacity))
    oldest, _ = candidates[0]
    if now - oldest[0].enqueued_at >= limits.max_wait_s:
        return oldest, None
    full = [batch for batch, is_full in candidates if is_full]
    if full:
        return full[0], None
    if incoming == 0:
        return oldest, None
    return [], oldest[0].enqueued_at + limits.max_wait_s - now


@dataclass(frozen=True)
class ComputeTime:
    """Running means over the batches of one model, in units of work (what the adapter's `work`
    counts: for stereo, padded pixels of a plain request, see `service.batching.stereo`)."""

    seconds_per_work: float  # compute seconds per unit of work of a batch
    work_per_request: float  # units of work of one request

    def seconds(self, work: float) -> float:
        """Estimated compute seconds of `work` units."""
        return work * self.seconds_per_work


class ComputeTimes:
    """Measured compute time per model: exponential running means, `weight` on the newest batch.
    Measured per unit of work, so that requests with costly options (many iterations, two-pass)
    or cheap ones (a small scale) neither skew the estimate of plain requests nor are misjudged."""

    def __init__(self, weight: float = 0.2) -> None:
        self._weight = weight
        self._means: dict[str, ComputeTime] = {}

    def get(self, model: str) -> ComputeTime | None:
        """The running means of `model`; None before its first batch."""
        return self._means.get(model)

    def record(self, model: str, work: float, batch_size: int, seconds: float) -> None:
        """A batch of `batch_size` requests of `work` units each took `seconds`."""
        newest = ComputeTime(seconds / (batch_size * work), float(work))
        previous = self._means.get(model)
        if previous is not None:
            newest = ComputeTime(
                self._mix(previous.seconds_per_work, newest.seconds_per_work),
                self._mix(previous.work_per_request, newest.work_per_request),
            )
        self._means[model] = newest

    def _mix(self, previous: float, newest: float) -> float:
        return (1 - self._weight) * previous + self._weight * newest
