"""What the served uncertainty means: a probability of a large disparity error.

The paper's U = 1 - sigmoid(var(V)) of the last iteration (model.uncertainty) ranks pixels but has
no unit (and is at most 0.5 after the first iteration), and on its own it barely tells the pixels
that are wrong from those that are right. A calibration, fitted on procedural validation scenes
for one set of weights and stored in the weights file (`training.calibrate`), maps it to

    P(|disparity error| > threshold_px)

in two steps: a confidence score, a logistic function of per-pixel features of the answer
(`confidence_features`: U and its neighbourhood, disparity edges, image texture, matches that
fall outside the right image, the disparity itself), then a non-decreasing piecewise-linear map of
that score to the probability. Files fitted before the features existed score by U alone.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from itertools import pairwise
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

FEATURES = ("uncertainty", "uncertainty_nearby", "disparity_edges", "texture", "outside_right_view", "log_disparity")
"""The per-pixel features of the confidence score, in the order of `confidence_features`."""
NEIGHBOURHOOD_PX = 9
"""Side of the square window of the neighbourhood features (mean U, texture, edge maximum)."""


def confidence_features(raw: Tensor, disparity: Tensor, left: Tensor) -> Tensor:
    """The features (B, len(FEATURES), H, W) of each pixel's answer, from the paper's U `raw`
    (B, 1, H, W), the `disparity` (B, 1, H, W; positive px of the left image) and the `left`
    image (B, 3, H, W; RGB in [0, 255]): U; U's mean over the neighbourhood; log(1 + the largest
    disparity gradient (px/px) nearby): depth edges, where occlusions and fattening are; log(1 +
    the mean squared grey gradient nearby): texture; 1 where the match x - d falls left of the
    right image, else 0; log(1 + d). Convolutions and pooling only, so it exports to ONNX."""
    window, half = NEIGHBOURHOOD_PX, NEIGHBOURHOOD_PX // 2
    grey = left.mean(dim=1, keepdim=True)
    grey_x, grey_y = _sobel(grey)
    texture = torch.log1p(F.avg_pool2d(grey_x**2 + grey_y**2, window, 1, half, count_include_pad=False))
    disparity_x, disparity_y = _sobel(disparity)
    edges = torch.log1p(F.max_pool2d(torch.sqrt(disparity_x**2 + disparity_y**2 + 1e-12), window, 1, half))
    column = torch.arange(disparity.shape[-1], device=disparity.device, dtype=disparity.dtype)
    outside = (column - disparity < 0).to(disparity.dtype)
    nearby = F.avg_pool2d(raw, window, 1, half, count_include_pad=False)
    return torch.cat([raw, nearby, edges, texture, outside, torch.log1p(disparity.clamp(min=0.0))], dim=1)


def _sobel(image: Tensor) -> tuple[Tensor, Tensor]:
    """Horizontal and vertical 3x3 Sobel derivatives of (B, 1, H, W), borders replicated."""
    kernel_x = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]], device=image.device)
    kernels = torch.stack([kernel_x, kernel_x.t()])[:, None].to(image.dtype)
    derivatives = F.conv2d(F.pad(image, (1, 1, 1, 1), mode="replicate"), kernels)
    return derivatives[:, :1], derivatives[:, 1:]


def score_design(features: Tensor, mean: Tensor, scale: Tensor) -> Tensor:
    """The terms of the confidence score, (B, 2F + 1, H, W): the standardised features, their
    squares and a constant, from features (B, F, H, W) and per-feature `mean` and `scale` (F,)."""
    standard = (features - mean[:, None, None]) / scale[:, None, None]
    return torch.cat([standard, standard**2, torch.ones_like(standard[:, :1])], dim=1)


@dataclass(frozen=True)
class UncertaintyCalibration:
    """The map to P(error > threshold_px): a score, then the points (knots[i], probabilities[i])
    over it, knots increasing, probabilities non-decreasing; constant beyond the first and last.

    The score is sum_k coefficients[k] * score_design(features)[k] with the features standardised
    by feature_mean and feature_scale (`confidence_features`); without coefficients (files fitted
    before the features) it is the paper's U itself.
    fitted_on: what the fit saw (scenes, their size and disparity range, pixel count).
    """

    threshold_px: float
    knots: tuple[float, ...]
    probabilities: tuple[float, ...]
    fitted_on: str
    feature_mean: tuple[float, ...] = ()
    feature_scale: tuple[float, ...] = ()
    coefficients: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if len(self.knots) != len(self.probabilities) or len(self.knots) < 2:
            raise ValueError("a calibration needs at least two (knot, probability) points")
        if any(b <= a for a, b in pairwise(self.knots)):
            raise ValueError("calibration knots must increase")
        if any(b < a for a, b in pairwise(self.probabilities)):
            raise ValueError("calibrated probabilities must not decrease")
        if self.coefficients and not (
            len(self.feature_mean) == len(self.feature_scale) == len(FEATURES)
            and len(self.coefficients) == 2 * len(FEATURES) + 1
        ):
            raise ValueError(
                f"a feature score needs {len(FEATURES)} means and scales and {2 * len(FEATURES) + 1} coefficients"
            )

    def score(self, raw: Tensor, disparity: Tensor, left: Tensor) -> Tensor:
        """The confidence score (B, 1, H, W) of each pixel (larger: more likely wrong); see the class."""
        return self.feature_score(confidence_features(raw, disparity, left)) if self.coefficients else raw

    def feature_score(self, features: Tensor) -> Tensor:
        """The score (B, 1, H, W) of features (B, len(FEATURES), H, W) as `confidence_features` gives them."""
        mean, scale, coefficients = (
            torch.tensor(values, device=features.device, dtype=features.dtype)
            for values in (self.feature_mean, self.feature_scale, self.coefficients)
        )
        design = score_design(features, mean, scale)
        return (design * coefficients[:, None, None]).sum(dim=1, keepdim=True)

    def apply(self, raw: Tensor, disparity: Tensor, left: Tensor) -> Tensor:
        """P(error > threshold_px), (B, 1, H, W), of the answer (`raw` U, `disparity`, `left` image
        as `confidence_features` takes them)."""
        return self.probability(self.score(raw, disparity, left))

    def probability(self, score: Tensor) -> Tensor:
        """The piecewise-linear map through the knots of a score (any shape), constant beyond the
        first and last knot, written as a sum of one clamped ramp per segment (elementwise ops
        only, so it exports to ONNX)."""
        probability = torch.full_like(score, self.probabilities[0])
        segments = zip(pairwise(self.knots), pairwise(self.probabilities), strict=True)
        for (x0, x1), (p0, p1) in segments:
            probability = probability + (score - x0).clamp(0.0, x1 - x0) * ((p1 - p0) / (x1 - x0))
        return probability

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @staticmethod
    def from_dict(values: dict[str, Any]) -> UncertaintyCalibration:
        def floats(key: str) -> tuple[float, ...]:
            return tuple(float(v) for v in values.get(key, ()))

        return UncertaintyCalibration(
            threshold_px=float(values["threshold_px"]),
            knots=floats("knots"),
            probabilities=floats("probabilities"),
            fitted_on=str(values["fitted_on"]),
            feature_mean=floats("feature_mean"),
            feature_scale=floats("feature_scale"),
            coefficients=floats("coefficients"),
        )
