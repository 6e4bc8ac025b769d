"""The batch scheduler's decisions, apart from its queues and the event loop (`service.batching`):
which requests may share a batch (`batch_key`), which batch runs next (`choose_batch`), and the
measured compute times that estimate the work ahead (`ComputeTimes`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, TypeVar

from model import Iterations, padded_size


@dataclass(frozen=True)
class Knobs:
    """The inference options of a request (`StereoPredictor.predict`'s keywords)."""

    two_pass: bool = False
    iters: Iterations = None
    scale: float = 1.0
    raw_uncertainty: bool = False


@dataclass(frozen=True)
class BatchKey:
    """Requests with equal keys may share a batch."""

    model: str
    knobs: Knobs
    height: int  # input shape of the batch: padded to a multiple of 32, or exact (see batch_key)
    width: int

    @property
    def pixels(self) -> int:
        return self.height * self.width


def batch_key(model: str, knobs: Knobs, height: int, width: int) -> BatchKey:
    """Plain requests batch by padded shape: padding them to it is what the network does anyway.
    Two-pass and scaled requests batch by exact shape, since their resized passes see the
    unpadded image."""
    if knobs.two_pass or knobs.scale != 1.0:
        return BatchKey(model, knobs, height, width)
    return BatchKey(model, knobs, padded_size(height), padded_size(width))


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
    """Running means over the batches of one model."""

    seconds_per_pixel: float  # compute seconds per padded pixel of a batch
    pixels_per_request: float  # padded pixels of one request

    def seconds(self, pixels: float) -> float:
        """Estimated compute seconds of `pixels` padded pixels."""
        return pixels * self.seconds_per_pixel


class ComputeTimes:
    """Measured compute time per model: exponential running means, `weight` on the newest batch."""

    def __init__(self, weight: float = 0.2) -> None:
        self._weight = weight
        self._means: dict[str, ComputeTime] = {}

    def get(self, model: str) -> ComputeTime | None:
        """The running means of `model`; None before its first batch."""
        return self._means.get(model)

    def record(self, model: str, pixels: int, batch_size: int, seconds: float) -> None:
        """A batch of `batch_size` requests of `pixels` padded pixels each took `seconds`."""
        newest = ComputeTime(seconds / (batch_size * pixels), float(pixels))
        previous = self._means.get(model)
        if previous is not None:
            newest = ComputeTime(
                self._mix(previous.seconds_per_pixel, newest.seconds_per_pixel),
                self._mix(previous.pixels_per_request, newest.pixels_per_request),
            )
        self._means[model] = newest

    def _mix(self, previous: float, newest: float) -> float:
        return (1 - self._weight) * previous + self._weight * newest
