"""Fit the meaning of the served uncertainty for one set of weights (see inference.uncertainty_calibration).

The fit runs the network on procedural validation scenes, never on real pairs: their seeds lie
in a range no training run draws (training seeds come from numpy generators seeded by
(seed, step, rank)), and they are rendered at a size and disparity range of their own.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from scipy.optimize import isotonic_regression

from crestereo_pp.inference import NETWORK_ONLY, StereoPredictor, load_model
from crestereo_pp.inference.uncertainty_calibration import (
    FEATURES,
    UncertaintyCalibration,
    confidence_features,
    score_design,
)
from crestereo_pp.model.weights import read_weights, write_weights
from crestereo_pp.stereo_data.synthetic import SceneConfig, SceneGenerator

CALIBRATION_SEED = 2**31
"""First seed of the calibration scenes: above every training seed (``synthetic.draw.SEEDS``)."""
CALIBRATION_SCENES = SceneConfig(height=256, width=512, max_disparity=96.0)
"""Size and disparity range of the calibration scenes: about a fifth of the width at most, like
the real pairs of KITTI and Middlebury at their native size."""


MAX_FIT_PIXELS = 2_000_000
"""Pixels the confidence score is fitted on at most (a seeded random subset beyond)."""


def fit_probability(
    score: np.ndarray, errors: np.ndarray, threshold_px: float, bins: int = 32
) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Fit score -> P(error > threshold_px) on flat arrays of scores and absolute errors (px): the
    frequency of large errors in `bins` quantile bins of the score, made non-decreasing by isotonic
    regression (weighted by bin size), placed at the bins' mean score. A tiny slope (1e-6 per bin)
    keeps the map strictly increasing, so the probabilities rank pixels as the score does.
    Returns the knots and their probabilities."""
    if score.shape != errors.shape or score.ndim != 1 or score.size < bins:
        raise ValueError(f"need equal flat arrays of at least {bins} values, got {score.shape} and {errors.shape}")
    order = np.argsort(score, kind="stable")
    groups = [group for group in np.array_split(order, bins) if group.size]
    means = np.array([score[group].mean() for group in groups])
    rates = np.array([(errors[group] > threshold_px).mean() for group in groups])
    sizes = np.array([group.size for group in groups], dtype=np.float64)
    distinct = np.concatenate([[True], np.diff(means) > 0])  # bins of one equal score: keep the first
    if distinct.sum() < 2:
        raise ValueError("the scores are all equal: nothing to calibrate")
    fitted = isotonic_regression(rates[distinct], weights=sizes[distinct]).x
    fitted = np.minimum(1.0, fitted + 1e-6 * np.arange(fitted.size))
    return tuple(float(v) for v in means[distinct]), tuple(float(v) for v in fitted)


def fit_calibration(
    features: np.ndarray, errors: np.ndarray, threshold_px: float, fitted_on: str, bins: int = 32
) -> UncertaintyCalibration:
    """Fit the calibration on per-pixel `features` (N, len(FEATURES), as `confidence_features`
    gives them) and absolute errors (N,) in px: a logistic regression of (error > threshold_px)
    on `score_design` of the standardised features (L2 penalty 1e-4, L-BFGS), then the isotonic
    map of its score to the probability (`fit_probability`)."""
    if features.ndim != 2 or features.shape != (errors.size, len(FEATURES)):
        raise ValueError(f"need features of shape (N, {len(FEATURES)}) and N errors, got {features.shape}")
    values = torch.from_numpy(features).double()
    mean, scale = values.mean(dim=0), values.std(dim=0).clamp(min=1e-6)
    design = score_design(values[:, :, None, None], mean, scale)[:, :, 0, 0]
    wrong = torch.from_numpy(errors > threshold_px).double()
    coefficients = torch.zeros(design.shape[1], dtype=torch.float64, requires_grad=True)
    optimizer = torch.optim.LBFGS([coefficients], max_iter=200, line_search_fn="strong_wolfe")

    def objective() -> torch.Tensor:
        optimizer.zero_grad()
        loss = F.binary_cross_entropy_with_logits(design @ coefficients, wrong) + 1e-4 * coefficients.square().sum()
        loss.backward()  # type: ignore[no-untyped-call]  # torch leaves it unannotated
        return loss

    optimizer.step(objective)  # type: ignore[no-untyped-call]
    score = (design @ coefficients.detach()).numpy()
    knots, probabilities = fit_probability(score, errors, threshold_px, bins)
    return UncertaintyCalibration(
        threshold_px=threshold_px,
        knots=knots,
        probabilities=probabilities,
        fitted_on=fitted_on,
        feature_mean=tuple(float(v) for v in mean),
        feature_scale=tuple(float(v) for v in scale),
        coefficients=tuple(float(v) for v in coefficients.detach()),
    )


def calibrate(
    predictor: StereoPredictor, scenes: int = 32, threshold_px: float = 2.0, batch_size: int = 4
) -> UncertaintyCalibration:
    """Fit the calibration of `predictor` on `scenes` procedural validation scenes (every pixel
    with ground truth, occluded ones included, as the evaluation counts them; at most
    MAX_FIT_PIXELS of them)."""
    generator = SceneGenerator(CALIBRATION_SCENES, device=predictor.device)
    features, errors = [], []
    for first in range(0, scenes, batch_size):
        count = min(batch_size, scenes - first)
        batch = generator.generate(count, seed=CALIBRATION_SEED + first)
        # the network's own answer: the served uncertainty is computed from it, before any host refinement
        prediction = predictor.predict(batch.left, batch.right, raw_uncertainty=True, **NETWORK_ONLY)
        assert isinstance(prediction.disparity, torch.Tensor)
        disparity = prediction.disparity[:, None]
        known = batch.valid[:, 0]
        maps = confidence_features(prediction.uncertainty[:, None], disparity, batch.left, batch.right)
        per_pixel = maps.permute(0, 2, 3, 1)
        features.append(per_pixel[known].cpu().numpy())
        errors.append((prediction.disparity - batch.disparity[:, 0]).abs()[known].cpu().numpy())
    all_features, all_errors = np.concatenate(features), np.concatenate(errors)
    if all_errors.size > MAX_FIT_PIXELS:
        kept = np.random.default_rng(0).choice(all_errors.size, MAX_FIT_PIXELS, replace=False)
        all_features, all_errors = all_features[kept], all_errors[kept]
    cfg = CALIBRATION_SCENES
    fitted_on = (
        f"{scenes} procedural scenes {cfg.height}x{cfg.width}, disparities 0-{cfg.max_disparity:g} px, "
        f"seeds from {CALIBRATION_SEED}, {all_errors.size:,} pixels"
    )
    return fit_calibration(all_features, all_errors, threshold_px, fitted_on)


def calibrate_weights_file(path: Path, scenes: int = 32) -> UncertaintyCalibration:
    """Fit the calibration of the weights (or checkpoint) at `path` and store it in the file
    under "calibration", replacing any earlier one."""
    payload = read_weights(path)
    # Fitted on the torch reference in fp32: every backend serves the maps it gives, up to rounding.
    predictor = load_model(str(payload.get("model_name") or "lite"), path, backend="torch", precision="fp32")
    calibration = calibrate(predictor, scenes)
    payload["calibration"] = calibration.to_dict()
    write_weights(payload, path)
    return calibration
