"""Fit the meaning of the served uncertainty for one set of weights (see model.calibration).

The fit runs the network on procedural validation scenes, never on real pairs: their seeds lie
in a range no training run draws (training seeds come from numpy generators seeded by
(seed, step, rank)), and they are rendered at a size and disparity range of their own.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from scipy.optimize import isotonic_regression

from model import StereoPredictor, load_model
from model.calibration import UncertaintyCalibration
from model.weights import read_weights, write_weights
from stereo_data.synthetic import SceneConfig, SceneGenerator

CALIBRATION_SEED = 2**40
"""First seed of the calibration scenes (far from any training seed)."""
CALIBRATION_SCENES = SceneConfig(height=256, width=512, max_disparity=96.0)
"""Size and disparity range of the calibration scenes: about a fifth of the width at most, like
the real pairs of KITTI and Middlebury at their native size."""


def fit_calibration(
    raw: np.ndarray, errors: np.ndarray, threshold_px: float, fitted_on: str, bins: int = 32
) -> UncertaintyCalibration:
    """Fit U -> P(error > threshold_px) on flat arrays of raw uncertainties and absolute errors
    (px): the frequency of large errors in `bins` quantile bins of U, made non-decreasing by
    isotonic regression (weighted by bin size), placed at the bins' mean U. A tiny slope (1e-6
    per bin) keeps the map strictly increasing, so the probabilities rank pixels as U does."""
    if raw.shape != errors.shape or raw.ndim != 1 or raw.size < bins:
        raise ValueError(f"need equal flat arrays of at least {bins} values, got {raw.shape} and {errors.shape}")
    order = np.argsort(raw, kind="stable")
    groups = [group for group in np.array_split(order, bins) if group.size]
    means = np.array([raw[group].mean() for group in groups])
    rates = np.array([(errors[group] > threshold_px).mean() for group in groups])
    sizes = np.array([group.size for group in groups], dtype=np.float64)
    distinct = np.concatenate([[True], np.diff(means) > 0])  # bins of one equal U: keep the first
    if distinct.sum() < 2:
        raise ValueError("the raw uncertainties are all equal: nothing to calibrate")
    fitted = isotonic_regression(rates[distinct], weights=sizes[distinct]).x
    fitted = np.minimum(1.0, fitted + 1e-6 * np.arange(fitted.size))
    return UncertaintyCalibration(
        threshold_px=threshold_px,
        knots=tuple(float(v) for v in means[distinct]),
        probabilities=tuple(float(v) for v in fitted),
        fitted_on=fitted_on,
    )


def calibrate(
    predictor: StereoPredictor, scenes: int = 24, threshold_px: float = 2.0, batch_size: int = 4
) -> UncertaintyCalibration:
    """Fit the calibration of `predictor` on `scenes` procedural validation scenes (every pixel
    with ground truth, occluded ones included, as the evaluation counts them)."""
    generator = SceneGenerator(CALIBRATION_SCENES, device=predictor.device)
    raw_values, errors = [], []
    for first in range(0, scenes, batch_size):
        count = min(batch_size, scenes - first)
        batch = generator.generate(count, seed=CALIBRATION_SEED + first)
        prediction = predictor.predict(batch.left, batch.right, raw_uncertainty=True)
        assert isinstance(prediction.disparity, torch.Tensor)
        known = batch.valid[:, 0]
        raw_values.append(prediction.uncertainty[known].cpu().numpy())
        errors.append((prediction.disparity - batch.disparity[:, 0]).abs()[known].cpu().numpy())
    cfg = CALIBRATION_SCENES
    fitted_on = (
        f"{scenes} procedural scenes {cfg.height}x{cfg.width}, disparities 0-{cfg.max_disparity:g} px, "
        f"seeds from {CALIBRATION_SEED}"
    )
    return fit_calibration(np.concatenate(raw_values), np.concatenate(errors), threshold_px, fitted_on)


def calibrate_weights_file(path: Path, scenes: int = 24) -> UncertaintyCalibration:
    """Fit the calibration of the weights (or checkpoint) at `path` and store it in the file
    under "calibration", replacing any earlier one."""
    payload = read_weights(path)
    # Fitted on the torch reference in fp32: every backend serves the maps it gives, up to rounding.
    predictor = load_model(str(payload.get("model_name") or "lite"), path, backend="torch", precision="fp32")
    calibration = calibrate(predictor, scenes)
    payload["calibration"] = calibration.to_dict()
    write_weights(payload, path)
    return calibration
