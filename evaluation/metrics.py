"""Disparity error metrics, as used by the Middlebury, ETH3D and KITTI benchmarks.

Every metric is computed over the pixels where the ground truth is valid (occluded pixels
included), from the absolute error |prediction - ground truth| in pixels.
"""

from __future__ import annotations

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
