"""How a pair is computed: one type for the per-call inference options and the one parser of
iteration counts. The HTTP query, the command line, the service's batch key and the predictor all
speak `InferenceOptions`; the backend and precision are the predictor's own (``load_model``); a
video's frames add a warm start (``inference.warm_start``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal, TypedDict

StageCounts = tuple[int, int, int]
"""ARM iterations of the three stages, at 1/16, 1/8 and 1/4 resolution (what the network runs)."""

Iterations = int | StageCounts | None
"""What a caller asks for: None, the model's counts; an int, the finest (1/4) stage's; or the
three `StageCounts`. `StereoPredictor.iterations` resolves it to `StageCounts`."""

IterationsGiven = str | int | Sequence[int] | None
"""Iterations as a caller gives them: text ("4", "1,2,4"), one count, a sequence of counts, or
None; ``parse_iterations`` reads them as ``Iterations``."""

TwoPass = bool | Literal["auto"]
"""Whether a cold pair is computed in two passes (a half-resolution pass, then refinement at full
resolution from it): True, False, or "auto": a quick quarter-resolution pass decides, two passes
where it finds large disparities, one elsewhere, either way on the pair enlarged up to 1.5x as far
as their range allows, or shrunk where two passes could not hold it (``inference.two_pass.auto_way``)."""

TWO_PASS_CHOICES = ("auto", "on", "off")
"""``TwoPass`` as the command line and other text spell it (``parse_two_pass``)."""

MAX_ITERATIONS = 99
"""Most ARM iterations per stage that a caller may ask for (the 1..MAX_ITERATIONS rule is
``parse_iterations``'s; ``ITERATIONS_PATTERN`` spells it for text). A run of nines, so that a
count's text is "a digit 1-9, then up to len(str(MAX_ITERATIONS)) - 1 digits"."""

_COUNT_PATTERN = "[1-9]" + "[0-9]?" * (len(str(MAX_ITERATIONS)) - 1)
ITERATIONS_PATTERN = f"^{_COUNT_PATTERN}(,{_COUNT_PATTERN},{_COUNT_PATTERN})?$"
"""The text ``parse_iterations`` reads, as a regular expression: one count or three
comma-separated ones, each 1..MAX_ITERATIONS (the HTTP query's ``iters`` pattern)."""


def parse_iterations(value: IterationsGiven) -> Iterations:
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
        raise ValueError(f"two_pass is auto, on (true) or off (false), got {value!r}")
    return spelled


def parse_scale(scale: float) -> float:
    """``scale`` as given, where it is in (0, 1] (the factor the pair is resized by before the
    network sees it); ValueError otherwise."""
    if not 0.0 < scale <= 1.0:
        raise ValueError(f"scale must be in (0, 1], got {scale}")
    return scale


class HostSteps(TypedDict):
    """The classical steps around the network, as ``predict`` keywords (see ``InferenceOptions``)."""

    blend_sgbm: bool
    refine_edges: bool
    align_rows: bool


NETWORK_ONLY: HostSteps = {"blend_sgbm": False, "refine_edges": False, "align_rows": False}
"""``predict`` keywords for the network's own answer on the pair as given: no row alignment
before it, no SGBM blend or edge refinement after it (the calibration's fit, training's
validation, speed benchmarks of the network)."""


@dataclass(frozen=True, init=False)
class InferenceOptions:
    """The options of one prediction (``StereoPredictor.predict`` and ``predict_batch``), read once
    where a request comes in: the constructor is the one reader of what the HTTP query, the
    command line and Python callers give (``parse_iterations``, ``parse_two_pass``, the scale's
    range), so the value that travels is checked and normalised.

    iters: see ``Iterations`` (given in any form ``parse_iterations`` reads); the predictor
        resolves it against its model's counts (``StereoPredictor.iterations``).
    two_pass: a half-resolution pass first, then refinement at full resolution from it: always
        (True), never (False), or where the pair has large disparities ("auto"; see ``TwoPass``).
    scale: in (0, 1]: the network sees the pair resized by this factor; maps come at input size.
    raw_uncertainty: the paper's U instead of the calibrated probability of an error.
    flip: also compute the pair upside down and merge the two answers (``inference.flip``):
        about twice the time, fewer large errors.
    blend_sgbm: average the answer with OpenCV's SGBM where the two agree within 4 px
        (``inference.sgbm``): one SGBM run more (about 5 % of the default's time on a CPU),
        fewer errors over 1 and 2 px.
    refine_edges: refine the answer at its edges: put its depth edges where the left image's
        colour edges are, by a colour-weighted median of the disparities near them
        (``inference.depth_edges``), then raise the strip along the image's left edge whose
        matches fall outside the right image towards the surface beside it, by 4 px at most
        (``inference.border_strip``): under 10 % more time on a CPU, fewer errors at the edges of
        objects and of the image. With ``blend_sgbm`` False too, the network's own answer is served.
    align_rows: where the right image's rows are off the left's by a quarter pixel or more
        (measured on the pair from tracked corners: ``inference.row_alignment``), resample the
        right image onto them first: about 20 ms a pair on a CPU; residual misrectification
        costs the network much of its precision. Pairs given as arrays; tensors go as given.
    Hashable: requests with equal options (and shapes) may share a batch.
    """

    iters: Iterations
    two_pass: TwoPass
    scale: float
    raw_uncertainty: bool
    flip: bool
    blend_sgbm: bool
    refine_edges: bool
    align_rows: bool

    def __init__(
        self,
        iters: IterationsGiven = None,
        two_pass: str | bool = "auto",
        scale: float = 1.0,
        raw_uncertainty: bool = False,
        flip: bool = False,
        blend_sgbm: bool = True,
        refine_edges: bool = True,
        align_rows: bool = True,
    ) -> None:
        object.__setattr__(self, "iters", parse_iterations(iters))
        object.__setattr__(self, "two_pass", parse_two_pass(two_pass))
        object.__setattr__(self, "scale", parse_scale(scale))
        object.__setattr__(self, "raw_uncertainty", raw_uncertainty)
        object.__setattr__(self, "flip", flip)
        object.__setattr__(self, "blend_sgbm", blend_sgbm)
        object.__setattr__(self, "refine_edges", refine_edges)
        object.__setattr__(self, "align_rows", align_rows)

    def keywords(self) -> dict[str, Any]:
        """The options as ``predict`` / ``predict_batch`` keywords."""
        return {
            "iters": self.iters,
            "two_pass": self.two_pass,
            "scale": self.scale,
            "raw_uncertainty": self.raw_uncertainty,
            "flip": self.flip,
            "blend_sgbm": self.blend_sgbm,
            "refine_edges": self.refine_edges,
            "align_rows": self.align_rows,
        }
