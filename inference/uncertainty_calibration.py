"""What the served uncertainty means: a probability of a large disparity error.

The paper's U = 1 - sigmoid(var(V)) of the last iteration (model.uncertainty) ranks pixels but has
no unit (and is at most 0.5 after the first iteration), and on its own it barely tells the pixels
that are wrong from those that are right. A calibration, fitted on procedural validation scenes
for one set of weights and stored in the weights file (`training.calibrate`), maps it to

    P(|disparity error| > threshold_px)

in two steps: a confidence score, a logistic function of per-pixel features of the answer
(`confidence_features`: U and its neighbourhood, disparity edges, image texture, matches that
fall outside the right image, the disparity itself, and how well the right image matches at the
answer and at other disparities nearby), then a non-decreasing piecewise-linear map of that score
to the probability. Files fitted before the features existed score by U alone; files fitted before
the match features use the first six features only.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from itertools import pairwise
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from crestereo_pp.model.warping import bilinear_warp

ANSWER_FEATURES = (
    "uncertainty",
    "uncertainty_nearby",
    "disparity_edges",
    "texture",
    "outside_right_view",
    "log_disparity",
)
"""The features read from the answer and the left image alone (`answer_features`)."""
MATCH_FEATURES = ("match_dissimilarity", "match_ambiguity")
"""The features that compare the left image with the right one at the answer (`match_features`)."""
FEATURES = ANSWER_FEATURES + MATCH_FEATURES
"""The per-pixel features of the confidence score, in the order of `confidence_features`."""
NEIGHBOURHOOD_PX = 9
"""Side of the square window of the neighbourhood features (mean U, texture, edge maximum)."""
MATCH_WINDOW_PX = 5
"""Side of the square window of the match features' correlation, at half resolution (about 10
pixels of the image)."""
AMBIGUITY_OFFSETS_PX = (-12.0, -4.0, 4.0, 12.0)
"""The other disparities the match is compared with, as offsets (px of the image) from the answer."""
CENTRING_WINDOW_PX = 15
"""Side of the square window (at half resolution, about 30 pixels of the image) whose mean the
match features subtract from each grey image first. It is nearly constant over a correlation
window, so the correlation hardly changes, but it keeps the windows' sums small: a variance is a
difference of two sums, and of raw grey levels (squares up to 255^2) float32 lost about 1e-3 of a
correlation in flat windows, rounded differently by each runtime."""
ZNCC_VARIANCE_FLOOR = 4.0
"""Added to the product of the two windows' grey variances (grey levels^4) under the correlation's
square root, so that flat windows correlate near 0, not at random."""


def confidence_features(
    raw: Tensor, disparity: Tensor, left: Tensor, right: Tensor, count: int = len(FEATURES)
) -> Tensor:
    """The first `count` features (B, count, H, W) of FEATURES for each pixel's answer: the
    `answer_features` of the paper's U `raw` (B, 1, H, W), the `disparity` (B, 1, H, W; positive
    px of the left image) and the `left` image (B, 3, H, W; RGB in [0, 255]), then the
    `match_features` of the `left` and `right` images (B, 3, H, W) at that disparity (computed only
    when `count` asks for them)."""
    answer = answer_features(raw, disparity, left)
    if count <= len(ANSWER_FEATURES):
        return answer[:, :count]
    return torch.cat([answer, match_features(disparity, left, right)], dim=1)[:, :count]


def answer_features(raw: Tensor, disparity: Tensor, left: Tensor) -> Tensor:
    """ANSWER_FEATURES (B, 6, H, W) from the paper's U `raw` (B, 1, H, W), the `disparity`
    (B, 1, H, W; px) and the `left` image (B, 3, H, W; RGB in [0, 255]): U; U's mean over the
    neighbourhood; log(1 + the largest disparity gradient (px/px) nearby): depth edges, where
    occlusions and fattening are; log(1 + the mean squared grey gradient nearby): texture; 1 where
    the match x - d falls left of the right image, else 0; log(1 + d). Convolutions and pooling
    only, so it exports to ONNX."""
    grey = left.mean(dim=1, keepdim=True)
    grey_x, grey_y = _sobel(grey)
    texture = torch.log1p(_box_mean(grey_x**2 + grey_y**2, NEIGHBOURHOOD_PX))
    disparity_x, disparity_y = _sobel(disparity)
    edges = torch.log1p(_box_max(torch.sqrt(disparity_x**2 + disparity_y**2 + 1e-12), NEIGHBOURHOOD_PX))
    column = torch.arange(disparity.shape[-1], device=disparity.device, dtype=disparity.dtype)
    outside = (column - disparity < 0).to(disparity.dtype)
    nearby = _box_mean(raw, NEIGHBOURHOOD_PX)
    return torch.cat([raw, nearby, edges, texture, outside, torch.log1p(disparity.clamp(min=0.0))], dim=1)


def match_features(disparity: Tensor, left: Tensor, right: Tensor) -> Tensor:
    """MATCH_FEATURES (B, 2, H, W): how the grey `left` image (B, 3, H, W; RGB in [0, 255])
    matches the grey `right` image warped to it by the `disparity` d (B, 1, H, W; px;
    `model.warping.bilinear_warp`: x - d, zeros beyond the image), by
    zero-mean normalised cross-correlation (ZNCC) over MATCH_WINDOW_PX windows at half resolution
    (of the images less their local mean, CENTRING_WINDOW_PX):
    1 - ZNCC at the answer (0: the windows agree, up to 2: inverted), and the best ZNCC at the
    answer + AMBIGUITY_OFFSETS_PX minus the ZNCC at the answer (above 0: another disparity nearby
    matches better, as wrong matches and repeated patterns do). Each brought back to H x W
    bilinearly. Pooling, sampling and elementwise ops only, so it exports to ONNX."""
    height, width = disparity.shape[-2:]
    half_left, half_right = (_half_resolution_detail(image) for image in (left, right))
    half_disparity = F.avg_pool2d(disparity, 2, ceil_mode=True) / 2.0
    left_mean = _box_mean(half_left, MATCH_WINDOW_PX)
    left_variance = (_box_mean(half_left**2, MATCH_WINDOW_PX) - left_mean**2).clamp(min=0.0)

    def zncc(shift_px: float) -> Tensor:
        matched = bilinear_warp(half_right, (half_disparity + shift_px / 2.0).clamp(min=0.0))
        matched_mean = _box_mean(matched, MATCH_WINDOW_PX)
        matched_variance = (_box_mean(matched**2, MATCH_WINDOW_PX) - matched_mean**2).clamp(min=0.0)
        covariance = _box_mean(half_left * matched, MATCH_WINDOW_PX) - left_mean * matched_mean
        return covariance / torch.sqrt(left_variance * matched_variance + ZNCC_VARIANCE_FLOOR)

    at_answer = zncc(0.0)
    best_elsewhere = torch.stack([zncc(offset) for offset in AMBIGUITY_OFFSETS_PX]).amax(dim=0)
    half_features = torch.cat([1.0 - at_answer, best_elsewhere - at_answer], dim=1)
    return F.interpolate(half_features, size=(height, width), mode="bilinear", align_corners=False)


def _half_resolution_detail(image: Tensor) -> Tensor:
    """The grey of the (B, 3, H, W) `image` at half resolution, (B, 1, ceil(H/2), ceil(W/2)), minus
    its mean over CENTRING_WINDOW_PX."""
    grey = F.avg_pool2d(image.mean(dim=1, keepdim=True), 2, ceil_mode=True)
    return grey - _box_mean(grey, CENTRING_WINDOW_PX)


def _box_mean(image: Tensor, window: int) -> Tensor:
    """The mean of (B, C, H, W) over the `window` x `window` square around each pixel (odd
    `window`), of the pixels inside the image only; as a row pass and a column pass."""
    half = window // 2
    rows = F.avg_pool2d(image, (1, window), 1, (0, half), count_include_pad=False)
    return F.avg_pool2d(rows, (window, 1), 1, (half, 0), count_include_pad=False)


def _box_max(image: Tensor, window: int) -> Tensor:
    """The largest value of (B, C, H, W) in the `window` x `window` square around each pixel (odd
    `window`); as a row pass and a column pass."""
    half = window // 2
    rows = F.max_pool2d(image, (1, window), 1, (0, half))
    return F.max_pool2d(rows, (window, 1), 1, (half, 0))


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
    by feature_mean and feature_scale (`confidence_features`: the first len(feature_mean) of
    FEATURES, all of them or the answer's six of files fitted before the match features); without
    coefficients (files fitted before the features) it is the paper's U itself.
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
        counts = (len(ANSWER_FEATURES), len(FEATURES))
        if self.coefficients and not (
            len(self.feature_mean) in counts
            and len(self.feature_scale) == len(self.feature_mean)
            and len(self.coefficients) == 2 * len(self.feature_mean) + 1
        ):
            raise ValueError(
                f"a feature score needs the first {len(ANSWER_FEATURES)} or all {len(FEATURES)} features' means and "
                "scales, as many of each, and two coefficients per feature and one more"
            )

    @property
    def feature_count(self) -> int:
        """How many of FEATURES (the first ones) the score reads; 0 for a score by U alone."""
        return len(self.feature_mean)

    def score(self, raw: Tensor, disparity: Tensor, left: Tensor, right: Tensor) -> Tensor:
        """The confidence score (B, 1, H, W) of each pixel (larger: more likely wrong); see the class."""
        if not self.coefficients:
            return raw
        return self.feature_score(confidence_features(raw, disparity, left, right, self.feature_count))

    def feature_score(self, features: Tensor) -> Tensor:
        """The score (B, 1, H, W) of features (B, feature_count, H, W) as `confidence_features` gives them."""
        mean, scale, coefficients = (
            torch.tensor(values, device=features.device, dtype=features.dtype)
            for values in (self.feature_mean, self.feature_scale, self.coefficients)
        )
        design = score_design(features, mean, scale)
        return (design * coefficients[:, None, None]).sum(dim=1, keepdim=True)

    def apply(self, raw: Tensor, disparity: Tensor, left: Tensor, right: Tensor) -> Tensor:
        """P(error > threshold_px), (B, 1, H, W), of the answer (`raw` U, `disparity`, `left` and
        `right` images as `confidence_features` takes them)."""
        return self.probability(self.score(raw, disparity, left, right))

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
