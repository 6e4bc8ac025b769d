"""How a pair is computed: one type for the per-call inference options, the one parser of
iteration counts, and the warm start of a video's frames. The HTTP query, the command line, the
service's batch key and the predictor all speak `InferenceOptions`; the backend and precision are
the predictor's own (``load_model``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np

StageCounts = tuple[int, int, int]
"""ARM iterations of the three stages, at 1/16, 1/8 and 1/4 resolution (what the network runs)."""

Iterations = int | StageCounts | None
"""What a caller asks for: None, the model's counts; an int, the finest (1/4) stage's; or the
three `StageCounts`. `StereoPredictor.iterations` resolves it to `StageCounts`."""

TwoPass = bool | Literal["auto"]
"""Whether a cold pair is computed in two passes (a half-resolution pass, then refinement at full
resolution from it): True, False, or "auto": two passes only where a quick quarter-resolution pass
finds large disparities (see ``StereoPredictor.large_disparity_percentile``)."""

TWO_PASS_CHOICES = ("auto", "on", "off")
"""``TwoPass`` as the command line and other text spell it (``parse_two_pass``)."""

MAX_ITERATIONS = 99
"""Most ARM iterations per stage that a caller may ask for."""


def parse_iterations(value: str | int | Sequence[int] | None) -> Iterations:
    """Iteration counts as given anywhere ("4", "1,2,4", 4, [1, 2, 4], (1, 2, 4), or None for the
    model's) as ``Iterations``: one count or three, each 1..MAX_ITERATIONS; ValueError otherwise."""
    if value is None:
        return None
    if isinstance(value, str):
        try:
            counts = tuple(int(part) for part in value.split(","))
        except ValueError:
            raise ValueError(f"iterations take 1 or 3 comma-separated counts, got {value!r}") from None
    elif isinstance(value, int):
        counts = (value,)
    else:
        counts = tuple(value)
    if len(counts) not in (1, 3) or not all(isinstance(n, int) for n in counts):
        raise ValueError(f"iterations take 1 or 3 counts (at 1/4, or at 1/16, 1/8, 1/4), got {value!r}")
    if not all(1 <= n <= MAX_ITERATIONS for n in counts):
        raise ValueError(f"each iteration count must be 1..{MAX_ITERATIONS}, got {value!r}")
    return counts[0] if len(counts) == 1 else (counts[0], counts[1], counts[2])


def parse_two_pass(value: str | bool) -> TwoPass:
    """``TwoPass`` from its spelling: "auto", "on"/"true" (True) or "off"/"false" (False), or a
    bool; ValueError otherwise."""
    if isinstance(value, bool):
        return value
    if value == "auto":
        return "auto"
    spelled = {"on": True, "true": True, "off": False, "false": False}.get(str(value).lower())
    if spelled is None:
        raise ValueError(f"two_pass is auto, on or off, got {value!r}")
    return spelled


@dataclass(frozen=True)
class InferenceOptions:
    """The options of one prediction (``StereoPredictor.predict`` and ``predict_batch``).

    iters: see ``Iterations`` (given in any form ``parse_iterations`` reads).
    two_pass: a half-resolution pass first, then refinement at full resolution from it: always
        (True), never (False), or where the pair has large disparities ("auto"; see ``TwoPass``).
    scale: in (0, 1]: the network sees the pair resized by this factor; maps come at input size.
    raw_uncertainty: the paper's U instead of the calibrated probability of an error.
    Hashable: requests with equal options (and shapes) may share a batch.
    """

    iters: Iterations = None
    two_pass: TwoPass = "auto"
    scale: float = 1.0
    raw_uncertainty: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "iters", parse_iterations(self.iters))
        object.__setattr__(self, "two_pass", parse_two_pass(self.two_pass))
        if not 0.0 < self.scale <= 1.0:
            raise ValueError(f"scale must be in (0, 1], got {self.scale}")

    def keywords(self) -> dict[str, Any]:
        """The options as ``predict`` / ``predict_batch`` keywords."""
        return {
            "iters": self.iters,
            "two_pass": self.two_pass,
            "scale": self.scale,
            "raw_uncertainty": self.raw_uncertainty,
        }


class WarmStart:
    """The options and warm start of each next frame of one camera (a video, a stream).

    The first frame (and any frame of another size than its predecessor, or after ``restart``)
    is computed cold with ``options``; each other one runs every stage with ``warm_iters``
    iterations (default: those of ``options``), without two_pass, its coarsest stage (1/16)
    starting from the previous frame's disparity instead of from zero. The finer stages re-derive
    the map from the frame's own images, so a static camera keeps the cold map (shipped lite on
    Middlebury Teddy, 20 frames: 0.05 px mean absolute difference from it, not growing; only a
    strip at the left edge whose match lies outside the right image, which has no evidence of
    its own, settles within a few frames nearer the truth). Refining the previous map at 1/4
    only, as warm frames did before, drifts: the 1/4 stage does not hold its own answer (3 more
    iterations from the cold map move it by 0.19 px), and every frame adds its move to the last
    one's (0.28 px after 20 frames; a pixel 26.6 -> 30.0 px). Fewer ``warm_iters`` than the cold
    frame's cost accuracy (warm frames keep the cold answer with as many iterations), not
    stability (tests/model/test_warm_start.py).
    """

    def __init__(self, options: InferenceOptions, warm_iters: Iterations = None) -> None:
        self.options = options
        self.warm_iters = parse_iterations(warm_iters)
        self._previous: np.ndarray | None = None

    def next(self, height: int, width: int) -> tuple[InferenceOptions, np.ndarray | None]:
        """The options of the next frame (of this size) and its warm start (float32 HxW px, or None: cold)."""
        previous = self._previous
        if previous is None or previous.shape != (height, width):
            return self.options, None
        iters = self.options.iters if self.warm_iters is None else self.warm_iters
        return replace(self.options, iters=iters, two_pass=False), previous

    def record(self, disparity: np.ndarray) -> None:
        """The disparity the frame just computed had (the next one starts from it)."""
        self._previous = disparity

    def restart(self) -> None:
        """Forget the previous frame (a cut): the next one is computed cold."""
        self._previous = None
