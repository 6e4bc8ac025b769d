"""The batch scheduler's decisions, apart from its queues and the event loop (`service.batching`):
which requests may share a batch (`batch_key`), which batch runs next (`choose_batch`), and the
measured compute times that estimate the work ahead (`ComputeTimes`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, TypeVar

from model import InferenceOptions, StageCounts, padded_size


@dataclass(frozen=True)
class BatchKey:
    """Requests with equal keys may share a batch."""

    model: str
    options: InferenceOptions
    height: int  # input shape of the batch: padded to a multiple of 32, or exact (see batch_key)
    width: int
    warm_start: bool = False  # each request starts from its own previous disparity (a stream's frames)

    @property
    def pixels(self) -> int:
        return self.height * self.width


def batch_key(model: str, options: InferenceOptions, height: int, width: int, warm_start: bool = False) -> BatchKey:
    """Plain requests batch by padded shape: padding them to it is what the network does anyway.
    Two-pass and scaled requests batch by exact shape, since their resized passes see the
    unpadded image. Warm-started requests batch only with warm-started ones (another graph)."""
    if options.two_pass or options.scale != 1.0:
        return BatchKey(model, options, height, width, warm_start)
    return BatchKey(model, options, padded_size(height), padded_size(width), warm_start)


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


# The cost model, fitted to lite on a 2-core CPU at 256x384 (measured / modelled time relative to
# the default 2,4,6: iterations 1,1,1 0.43 / 0.44; 8,8,16 1.88 / 2.13; 2,4,20 2.07 / 2.17;
# scale 0.5 0.22 / 0.25; two-pass 0.91 / 1.0). Coarse iterations cost more than their pixels
# suggest: per-operation overheads dominate at small sizes.
FIXED_COST = 3.5
"""What a forward costs besides its ARM iterations (feature extraction, upsampling), in ARM
iterations at 1/4 resolution."""
STAGE_WEIGHTS = (0.25, 0.5, 1.0)
"""The cost of one ARM iteration at 1/16, 1/8 and 1/4 resolution, relative to one at 1/4."""
TWO_PASS_COST = 1.0
"""Two-pass inference adds a pass at half resolution, and its warm start saves about as much."""


def relative_cost(counts: StageCounts, default_counts: StageCounts, scale: float, two_pass: bool) -> float:
    """Compute of a request relative to a plain one of the same size (the model's own iteration
    counts `default_counts`, scale 1, one pass): its iterations `counts` (at 1/16, 1/8, 1/4),
    `scale` (the network sees scale^2 of the pixels) and `two_pass`."""

    def forward(iterations: tuple[int, int, int]) -> float:
        return FIXED_COST + sum(weight * n for weight, n in zip(STAGE_WEIGHTS, iterations, strict=True))

    cost = forward(counts) / forward(default_counts) * scale**2
    return cost * TWO_PASS_COST if two_pass else cost


@dataclass(frozen=True)
class ComputeTime:
    """Running means over the batches of one model. A unit of work is one padded pixel of a plain
    request; a request with other options counts its `relative_cost` per pixel."""

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
