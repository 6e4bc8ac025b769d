"""Disparity error metrics, as used by the Middlebury, ETH3D and KITTI benchmarks.

Every metric is computed over the pixels where the ground truth is valid (occluded pixels
included), from the absolute error |prediction - ground truth| in pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

BAD_THRESHOLDS_PX: tuple[float, ...] = (1.0, 2.0, 3.0)
"""The N of the bad-N metrics reported everywhere (percent of valid pixels with error > N px)."""


@dataclass(frozen=True)
class DisparityMetrics:
    """Errors of one disparity map against its ground truth.

    epe: mean absolute error in pixels; bad1/bad2/bad3: percent of valid pixels with error
    greater than 1/2/3 px; d1_all: KITTI D1-all, percent of valid pixels with error greater
    than 3 px AND greater than 5 % of the true disparity; valid_pixels: how many pixels counted.
    """

    epe: float
    bad1: float
    bad2: float
    bad3: float
    d1_all: float
    valid_pixels: int


def bad_pixel_percent(errors: np.ndarray, threshold_px: float) -> float:
    """Percent of `errors` (flat, pixels) strictly greater than `threshold_px`; nan when empty."""
    if errors.size == 0:
        return float("nan")
    return float(100.0 * np.count_nonzero(errors > threshold_px) / errors.size)


def d1_all_percent(errors: np.ndarray, true_disparity: np.ndarray) -> float:
    """KITTI D1-all: percent of pixels with error > 3 px and > 5 % of the true disparity.

    errors, true_disparity: flat arrays over the same valid pixels. nan when empty.
    """
    if errors.size == 0:
        return float("nan")
    outliers = (errors > 3.0) & (errors > 0.05 * np.abs(true_disparity))
    return float(100.0 * np.count_nonzero(outliers) / errors.size)


def compute_metrics(prediction: np.ndarray, ground_truth: np.ndarray, valid: np.ndarray) -> DisparityMetrics:
    """All metrics of one prediction (float HxW, px) against ground truth (float HxW, px).

    valid: bool HxW; pixels whose ground truth is not finite never count, whatever `valid` says.
    """
    if prediction.shape != ground_truth.shape or valid.shape != ground_truth.shape:
        raise ValueError(
            f"shapes differ: prediction {prediction.shape}, ground truth {ground_truth.shape}, valid {valid.shape}"
        )
    counted = valid & np.isfinite(ground_truth)
    true_disparity = ground_truth[counted].astype(np.float64)
    errors = np.abs(prediction[counted].astype(np.float64) - true_disparity)
    bad1, bad2, bad3 = (bad_pixel_percent(errors, t) for t in BAD_THRESHOLDS_PX)
    return DisparityMetrics(
        epe=float(errors.mean()) if errors.size else float("nan"),
        bad1=bad1,
        bad2=bad2,
        bad3=bad3,
        d1_all=d1_all_percent(errors, true_disparity),
        valid_pixels=int(errors.size),
    )


def mean_metrics(per_pair: list[DisparityMetrics]) -> DisparityMetrics:
    """Unweighted mean over pairs of each metric (each pair counts once, whatever its size).

    valid_pixels of the result is the total over the pairs.
    """
    if not per_pair:
        raise ValueError("no pairs to average")

    def mean_of(field: str) -> float:
        return float(np.mean([getattr(m, field) for m in per_pair]))

    return DisparityMetrics(
        epe=mean_of("epe"),
        bad1=mean_of("bad1"),
        bad2=mean_of("bad2"),
        bad3=mean_of("bad3"),
        d1_all=mean_of("d1_all"),
        valid_pixels=sum(m.valid_pixels for m in per_pair),
    )


SPARSIFICATION_STEP_PERCENT = 5
"""The sparsification curve removes the most uncertain pixels in steps of this many percent."""


@dataclass(frozen=True)
class Sparsification:
    """How well an uncertainty (or any confidence) map ranks the errors of a disparity map
    (Poggi et al., "On the confidence of stereo matching in a deep-learning era", 2021).

    Removing the most uncertain pixels first, the error rate (bad-`threshold`) of what is left is
    measured at every density. removed_percent: 0, 5, ..., 95; bad_percent: bad-N (%) of the
    pixels kept there. auc: area under the error-rate curve (fraction) over density 0..1, computed
    pixel by pixel; auc_optimal: the area of a perfect ranking, eps + (1 - eps) ln(1 - eps) for
    the error rate eps at full density; auc_random: the area of a random ranking, eps. So
    auc / auc_optimal is 1 for a perfect map and eps / auc_optimal for a useless one.
    """

    threshold_px: float
    removed_percent: tuple[float, ...]
    bad_percent: tuple[float, ...]
    auc: float
    auc_optimal: float
    auc_random: float

    @property
    def ratio_to_optimal(self) -> float:
        """auc / auc_optimal (>= 1; 1 is perfect); nan when there is no error at all."""
        return self.auc / self.auc_optimal if self.auc_optimal > 0 else float("nan")

    @property
    def ratio_to_random(self) -> float:
        """auc / auc_random (1 is no better than chance, below 1 better); nan when there is no
        error at all."""
        return self.auc / self.auc_random if self.auc_random > 0 else float("nan")


def optimal_sparsification_auc(error_rate: float) -> float:
    """Area under the sparsification curve of a perfect ranking for error rate `error_rate` (a
    fraction): eps + (1 - eps) ln(1 - eps), 1 when every pixel is wrong."""
    if error_rate >= 1.0:
        return 1.0
    return error_rate + (1.0 - error_rate) * math.log1p(-error_rate)


def sparsification(errors: np.ndarray, uncertainty: np.ndarray, threshold_px: float = 2.0) -> Sparsification:
    """The sparsification curve and its areas for flat arrays of absolute errors (px) and
    uncertainties (larger = less trusted; ties keep pixel order) over the same valid pixels."""
    if errors.shape != uncertainty.shape or errors.ndim != 1 or errors.size == 0:
        raise ValueError(f"expected equal non-empty flat arrays, got {errors.shape} and {uncertainty.shape}")
    order = np.argsort(uncertainty, kind="stable")  # most trusted first
    bad = errors[order] > threshold_px
    kept = np.arange(1, bad.size + 1)
    error_rate_kept = np.cumsum(bad) / kept  # error rate of the k most trusted pixels, k = 1..N
    removed = tuple(float(r) for r in range(0, 100, SPARSIFICATION_STEP_PERCENT))
    at = [max(1, round(bad.size * (1.0 - r / 100.0))) for r in removed]
    epsilon = float(bad.mean())
    return Sparsification(
        threshold_px=threshold_px,
        removed_percent=removed,
        bad_percent=tuple(float(100.0 * error_rate_kept[k - 1]) for k in at),
        auc=float(error_rate_kept.mean()),
        auc_optimal=optimal_sparsification_auc(epsilon),
        auc_random=epsilon,
    )


def mean_sparsification(per_pair: list[Sparsification]) -> Sparsification:
    """Unweighted mean over pairs of the curve and the areas (each pair counts once)."""
    if not per_pair:
        raise ValueError("no pairs to average")
    return Sparsification(
        threshold_px=per_pair[0].threshold_px,
        removed_percent=per_pair[0].removed_percent,
        bad_percent=tuple(float(v) for v in np.mean([s.bad_percent for s in per_pair], axis=0)),
        auc=float(np.mean([s.auc for s in per_pair])),
        auc_optimal=float(np.mean([s.auc_optimal for s in per_pair])),
        auc_random=float(np.mean([s.auc_random for s in per_pair])),
    )


@dataclass(frozen=True)
class Reliability:
    """How well predicted probabilities of a large error match what happens (a reliability
    diagram): pixels binned by predicted probability into `bins` equal-width bins of [0, 1].

    predicted, observed: per bin, the mean predicted probability and the observed frequency of
    an error above threshold_px (nan for an empty bin); pixels: per bin, its pixel count;
    expected_calibration_error: sum over bins of pixels share x |predicted - observed|.
    """

    threshold_px: float
    predicted: tuple[float, ...]
    observed: tuple[float, ...]
    pixels: tuple[int, ...]
    expected_calibration_error: float

    @property
    def mean_predicted(self) -> float:
        """The mean predicted probability over all pixels."""
        return self._pixel_mean(self.predicted)

    @property
    def observed_rate(self) -> float:
        """The share of all pixels with an error above threshold_px."""
        return self._pixel_mean(self.observed)

    def _pixel_mean(self, per_bin: tuple[float, ...]) -> float:
        filled = [(value, count) for value, count in zip(per_bin, self.pixels, strict=True) if count]
        return sum(value * count for value, count in filled) / sum(count for _, count in filled)


def reliability(errors: np.ndarray, probability: np.ndarray, threshold_px: float, bins: int = 10) -> Reliability:
    """The reliability of `probability` (flat, predicted P(error > threshold_px)) against the
    flat absolute `errors` (px) over the same valid pixels."""
    if errors.shape != probability.shape or errors.ndim != 1 or errors.size == 0:
        raise ValueError(f"expected equal non-empty flat arrays, got {errors.shape} and {probability.shape}")
    which = np.clip((probability * bins).astype(np.int64), 0, bins - 1)
    bad = errors > threshold_px
    counts = np.bincount(which, minlength=bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        predicted = np.bincount(which, weights=probability, minlength=bins) / counts
        observed = np.bincount(which, weights=bad, minlength=bins) / counts
    filled = counts > 0
    ece = float(np.sum(counts[filled] / errors.size * np.abs(predicted[filled] - observed[filled])))
    return Reliability(
        threshold_px=threshold_px,
        predicted=tuple(float(v) for v in predicted),
        observed=tuple(float(v) for v in observed),
        pixels=tuple(int(c) for c in counts),
        expected_calibration_error=ece,
    )


def pool_reliability(per_pair: list[Reliability]) -> Reliability:
    """The reliability of all pixels of all pairs together (bins added up)."""
    if not per_pair:
        raise ValueError("no pairs to pool")
    counts = np.sum([r.pixels for r in per_pair], axis=0)
    predicted_sum = np.nansum([np.multiply(r.predicted, r.pixels) for r in per_pair], axis=0)
    observed_sum = np.nansum([np.multiply(r.observed, r.pixels) for r in per_pair], axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        predicted, observed = predicted_sum / counts, observed_sum / counts
    filled = counts > 0
    ece = float(np.sum(counts[filled] / counts.sum() * np.abs(predicted[filled] - observed[filled])))
    return Reliability(
        threshold_px=per_pair[0].threshold_px,
        predicted=tuple(float(v) for v in predicted),
        observed=tuple(float(v) for v in observed),
        pixels=tuple(int(c) for c in counts),
        expected_calibration_error=ece,
    )
