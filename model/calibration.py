"""What the served uncertainty means: the paper's U mapped to a probability of a large error.

The paper's U = 1 - sigmoid(var(V)) of the last iteration (model.uncertainty) ranks pixels but has
no unit (and is at most 0.5 after the first iteration). A calibration, fitted on procedural
validation scenes for one set of weights and stored in the weights file, maps it to

    P(|disparity error| > threshold_px)

by a non-decreasing piecewise-linear function of U (fitted by `training.calibrate`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from itertools import pairwise
from typing import Any

import torch
from torch import Tensor


@dataclass(frozen=True)
class UncertaintyCalibration:
    """U -> P(error > threshold_px) through the points (knots[i], probabilities[i]), knots
    increasing, probabilities non-decreasing; constant beyond the first and last knot.

    fitted_on: what the fit saw (scenes, their size and disparity range, pixel count).
    """

    threshold_px: float
    knots: tuple[float, ...]
    probabilities: tuple[float, ...]
    fitted_on: str

    def __post_init__(self) -> None:
        if len(self.knots) != len(self.probabilities) or len(self.knots) < 2:
            raise ValueError("a calibration needs at least two (knot, probability) points")
        if any(b <= a for a, b in pairwise(self.knots)):
            raise ValueError("calibration knots must increase")
        if any(b < a for a, b in pairwise(self.probabilities)):
            raise ValueError("calibrated probabilities must not decrease")

    def apply(self, raw: Tensor) -> Tensor:
        """P(error > threshold_px) for every value of `raw` (the paper's U, any shape): the
        piecewise-linear map through the knots, constant beyond the first and last, written as a
        sum of one clamped ramp per segment (elementwise ops only, so it exports to ONNX)."""
        probability = torch.full_like(raw, self.probabilities[0])
        segments = zip(pairwise(self.knots), pairwise(self.probabilities), strict=True)
        for (x0, x1), (p0, p1) in segments:
            probability = probability + (raw - x0).clamp(0.0, x1 - x0) * ((p1 - p0) / (x1 - x0))
        return probability

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @staticmethod
    def from_dict(values: dict[str, Any]) -> UncertaintyCalibration:
        return UncertaintyCalibration(
            threshold_px=float(values["threshold_px"]),
            knots=tuple(float(v) for v in values["knots"]),
            probabilities=tuple(float(v) for v in values["probabilities"]),
            fitted_on=str(values["fitted_on"]),
        )
