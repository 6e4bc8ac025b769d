"""The stereo side of batching, the adapter `service.batching.batcher.Batcher` runs: which requests may
share a batch (`StereoKey`, `stereo_key`), what a request costs (`relative_cost`, `options_cost`),
and how a batch of pairs is computed (`StereoBatches`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from crestereo_pp.inference import InferenceOptions, Iterations, PairMaps, StageCounts, TwoPass
from crestereo_pp.inference.backend_choice import Backend, Precision
from crestereo_pp.inference.row_alignment import RowOffset
from crestereo_pp.inference.two_pass import largest_enlargement
from crestereo_pp.inference.uncertainty_calibration import UncertaintyCalibration
from crestereo_pp.model import ModelConfig, padded_size


class Predictor(Protocol):
    """What the service needs from `inference.load_model(...)` (an `inference.StereoPredictor`)."""

    name: str
    weights_sha256: str | None
    calibration: UncertaintyCalibration | None
    training: dict[str, Any] | None
    backend: Backend
    precision: Precision

    @property
    def num_parameters(self) -> int: ...

    @property
    def trained(self) -> bool: ...

    @property
    def config(self) -> ModelConfig: ...

    def iterations(self, iters: Iterations) -> StageCounts: ...

    def ready(self, iters: Iterations = None, *, warm_start: bool = False) -> bool: ...

    def predict_pairs(
        self,
        lefts: Sequence[np.ndarray],
        rights: Sequence[np.ndarray],
        options: InferenceOptions,
        init_disparities: Sequence[np.ndarray] | None = None,
    ) -> PairMaps: ...


@dataclass(frozen=True)
class StereoKey:
    """Requests with equal keys may share a batch.

    options: the request's, as read where it came in (`DisparityOptions.inference`), handed
    unchanged to `StereoPredictor.predict_pairs`."""

    model: str
    options: InferenceOptions
    height: int  # input shape of the batch: padded to a multiple of 32, or exact (see stereo_key)
    width: int
    warm_start: bool = False  # each request starts from its own previous disparity (a stream's frames)

    @property
    def pixels(self) -> int:
        return self.height * self.width


def stereo_key(model: str, options: InferenceOptions, height: int, width: int, warm_start: bool = False) -> StereoKey:
    """Plain requests batch by padded shape: padding them to it is what the network does anyway.
    Two-pass (also "auto") and scaled requests batch by exact shape, since their resized passes
    see the unpadded image. Warm-started requests batch only with warm-started ones (another graph)."""
    if options.two_pass is not False or options.scale != 1.0:
        return StereoKey(model, options, height, width, warm_start)
    return StereoKey(model, options, padded_size(height), padded_size(width), warm_start)


# The cost model, fitted to lite on a 2-core CPU at 256x384 (measured / modelled time relative to
# the default 2,4,6: iterations 1,1,1 0.43 / 0.44; 8,8,16 1.88 / 2.13; 2,4,20 2.07 / 2.17;
# scale 0.5 0.22 / 0.25; two-pass 0.91 / 1.0). Coarse iterations cost more than their pixels
# suggest: per-operation overheads dominate at small sizes. Checked on the default backend
# (OpenVINO bf16, iterations without a graph on torch) with every classical step on, at 256x384 to
# 2048x2048 on a 2-core AVX512 CPU (bench/request_cost.py): measured / modelled 0.80-1.05 for
# iterations computed by torch (16,16,32: 8.1-9.7 plain requests measured, 9.9 modelled),
# 0.90-1.21 for flip (two runs), 1.08-1.18 for two passes, 0.90-1.12 for auto (counted as its
# largest enlargement, a bound); a scale of 0.5 cost 0.37-0.62 of a plain request over two runs
# (the most at 256x384, where the calls are short and this VM's timings noisy), counted 0.475
# (FULL_SIZE_SHARE; with the network's pixels alone it was counted 0.25).
FIXED_COST = 3.5
"""What a forward costs besides its ARM iterations (feature extraction, upsampling), in ARM
iterations at 1/4 resolution."""
STAGE_WEIGHTS = (0.25, 0.5, 1.0)
"""The cost of one ARM iteration at 1/16, 1/8 and 1/4 resolution, relative to one at 1/4."""
FULL_SIZE_SHARE = 0.3
"""The share of a request's time that stays at the pair's own size whatever its `scale`: the
classical steps and resampling the maps back (a scale of 0.5 measured 0.37-0.62 of a plain
request, bench/request_cost.py)."""
TWO_PASS_COST = 1.0
"""Two-pass inference adds a pass at half resolution, and its warm start saves about as much;
"auto" adds a pass at quarter resolution to one or the other (about 1/16 of the pixels)."""


def relative_cost(
    counts: StageCounts, default_counts: StageCounts, scale: float, two_pass: TwoPass, flip: bool = False
) -> float:
    """Compute of a request relative to a plain one of the same size (the model's own iteration
    counts `default_counts`, scale 1, one pass, no flip): its iterations `counts` (at 1/16, 1/8,
    1/4), `scale` (the network sees scale^2 of the pixels; FULL_SIZE_SHARE of the time does not
    shrink), `two_pass` and `flip` (all of it twice, the second time upside down)."""

    def forward(iterations: tuple[int, int, int]) -> float:
        return FIXED_COST + sum(weight * n for weight, n in zip(STAGE_WEIGHTS, iterations, strict=True))

    cost = forward(counts) / forward(default_counts) * (FULL_SIZE_SHARE + (1 - FULL_SIZE_SHARE) * scale**2)
    cost = cost * TWO_PASS_COST if two_pass is not False else cost
    return 2.0 * cost if flip else cost


FALLBACK_COST = 2.5
"""How much longer a forward takes on torch (fp32) than on OpenVINO (bf16), where OpenVINO has no
graph for its iterations yet (measured 2.0-2.9x on 2-core AVX512 CPUs, 384x512 to 2048x2048)."""


def options_cost(predictor: Predictor, options: InferenceOptions, warm_start: bool = False) -> float:
    """`relative_cost` of what `options` ask of `predictor`: their iterations (resolved against
    the model's own), scale, two passes and flip; times FALLBACK_COST where the predictor's
    backend has no graph for those iterations (and start) yet, so that torch computes them
    (`Predictor.ready`). 1.0 for the defaults on a ready backend; the enlargement "auto" may
    choose is the server's, not counted here."""
    counts = predictor.iterations(options.iters)
    cost = relative_cost(counts, predictor.config.iters, options.scale, options.two_pass, options.flip)
    return cost if predictor.ready(options.iters, warm_start=warm_start) else cost * FALLBACK_COST


@dataclass(frozen=True)
class StereoPair:
    """One request's input: a decoded pair (uint8 HxWx3 RGB) and its warm start (float32 HxW px,
    the previous frame of a stream), or None."""

    left: np.ndarray
    right: np.ndarray
    init: np.ndarray | None = None


@dataclass(frozen=True)
class StereoMaps:
    """One request's output: disparity (float32 HxW, px of the left image), uncertainty
    (float32 HxW in [0, 1]) and, where its options align rows, the right image's row offset as
    measured (None: too little texture to measure, or not measured)."""

    disparity: np.ndarray
    uncertainty: np.ndarray
    row_offset: RowOffset | None = None


class StereoBatches:
    """The batcher's adapter for stereo pairs: the cost of a request and the computation of a
    batch, by the model its key names."""

    def __init__(self, predictors: Mapping[str, Predictor]) -> None:
        self.predictors = predictors

    @property
    def models(self) -> list[str]:
        return list(self.predictors)

    def work(self, key: StereoKey) -> float:
        """Units of compute of one request of `key`: its padded pixels times `options_cost`, and,
        where "auto" may enlarge the pair, times the square of the largest factor it may take (an
        upper bound: a pair whose disparities are too large for that factor is computed smaller)."""
        options = key.options
        cost = options_cost(self.predictors[key.model], options, key.warm_start)
        if options.two_pass == "auto" and options.scale == 1.0 and not key.warm_start:
            cost *= largest_enlargement(key.height, key.width) ** 2
        return key.pixels * cost

    def compute(self, key: StereoKey, pairs: Sequence[StereoPair]) -> list[StereoMaps]:
        """Run one batch on the calling (inference) thread: `StereoPredictor.predict_pairs`, which pads
        every pair (and warm start) to the batch shape the way the network pads one; the maps
        come to the host at once."""
        inits = [pair.init for pair in pairs if pair.init is not None] if key.warm_start else None
        maps = self.predictors[key.model].predict_pairs(
            [pair.left for pair in pairs], [pair.right for pair in pairs], key.options, inits
        )
        offsets = maps.row_offsets or (None,) * len(pairs)
        return [
            StereoMaps(p.disparity, p.uncertainty, offset) for p, offset in zip(maps.on_host(), offsets, strict=True)
        ]
