"""The warm start of a video's frames: each next pair of one camera starts from its predecessor's
disparity (``WarmStart``, the rules; ``FrameStream``, a predictor's pairs computed that way)."""

from __future__ import annotations

from dataclasses import replace
from typing import Protocol

import numpy as np
from torch import Tensor

from .options import InferenceOptions, IterationsGiven, TwoPass, parse_iterations
from .prediction import Prediction


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
    stability (tests/inference/test_warm_start.py).
    """

    def __init__(self, options: InferenceOptions, warm_iters: IterationsGiven = None) -> None:
        self.options = options
        """A cold frame's options."""
        self.warm_options = replace(
            options, iters=options.iters if warm_iters is None else parse_iterations(warm_iters), two_pass=False
        )
        """A warm frame's options, read once for the whole stream (ValueError where `warm_iters` is invalid)."""
        self._previous: np.ndarray | None = None

    def next(self, height: int, width: int) -> tuple[InferenceOptions, np.ndarray | None]:
        """The options of the next frame (of this size) and its warm start (``start``)."""
        init = self.start(height, width)
        return (self.options if init is None else self.warm_options), init

    def start(self, height: int, width: int) -> np.ndarray | None:
        """The warm start of the next frame (of this size): the previous frame's disparity
        (float32 HxW px), or None where it is computed cold (with ``options``; else ``warm_options``)."""
        previous = self._previous
        return None if previous is None or previous.shape != (height, width) else previous

    def record(self, disparity: np.ndarray) -> None:
        """The disparity the frame just computed had (the next one starts from it)."""
        self._previous = disparity

    def restart(self) -> None:
        """Forget the previous frame (a cut): the next one is computed cold."""
        self._previous = None


class PairPredictor(Protocol):
    """What a ``FrameStream`` computes its pairs with (``StereoPredictor``)."""

    def predict(
        self,
        left: np.ndarray,
        right: np.ndarray | Tensor,
        *,
        iters: IterationsGiven = None,
        init_disparity: np.ndarray | Tensor | None = None,
        two_pass: TwoPass = "auto",
        scale: float = 1.0,
        raw_uncertainty: bool = False,
        flip: bool = False,
        blend_sgbm: bool = True,
        refine_edges: bool = True,
        align_rows: bool = True,
    ) -> Prediction: ...


class FrameStream:
    """Consecutive pairs of one camera computed one at a time, each warm-started from its
    predecessor (the rules, and why every stage runs, are ``WarmStart``'s)."""

    def __init__(self, predictor: PairPredictor, options: InferenceOptions, warm_iters: IterationsGiven = None) -> None:
        self.predictor = predictor
        self.warm_start = WarmStart(options, warm_iters)

    def predict(self, left: np.ndarray, right: np.ndarray) -> Prediction:
        """The maps of the next pair (arrays, as ``StereoPredictor.predict`` takes them)."""
        options, init = self.warm_start.next(*left.shape[:2])
        prediction = self.predictor.predict(left, right, init_disparity=init, **options.keywords())
        self.warm_start.record(prediction.disparity)
        return prediction

    def restart(self) -> None:
        """Forget the previous frame (a cut): the next pair is computed cold."""
        self.warm_start.restart()
