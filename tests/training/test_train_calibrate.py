"""Fitting the meaning of the uncertainty for a set of weights, on procedural scenes."""

import warnings

import numpy as np
import pytest
import torch

from crestereo_pp.inference import load_model
from crestereo_pp.inference.uncertainty_calibration import FEATURES
from crestereo_pp.model import CREStereoPP, ModelConfig
from crestereo_pp.training.calibrate import calibrate_weights_file, fit_calibration, fit_probability


def test_the_fit_recovers_a_known_error_probability_from_the_features_and_is_monotone():
    rng = np.random.default_rng(0)
    features = rng.random((60_000, len(FEATURES)))
    # wrong with probability 0.05, or 0.85 where the match falls outside the right image
    features[:, FEATURES.index("outside_right_view")] = rng.random(60_000) < 0.2
    truth = np.where(features[:, FEATURES.index("outside_right_view")] > 0, 0.85, 0.05)
    errors = np.where(rng.random(truth.size) < truth, 4.0, 0.5)
    calibration = fit_calibration(features, errors, 2.0, "test", bins=16)
    assert all(b > a for a, b in zip(calibration.probabilities, calibration.probabilities[1:], strict=False))
    rows = torch.from_numpy(features[:8, :, None, None])  # eight pixels as 1x1 maps
    predicted = calibration.probability(calibration.feature_score(rows)).flatten().numpy()
    np.testing.assert_allclose(predicted, truth[:8], atol=0.05)


def test_equal_scores_cannot_be_calibrated():
    with pytest.raises(ValueError, match="all equal"):
        fit_probability(np.full(100, 0.5), np.zeros(100), 2.0, bins=8)


def test_calibrating_a_weights_file_stores_a_fit_that_load_model_applies(tmp_path):
    torch.manual_seed(0)
    network = CREStereoPP(ModelConfig.preset("lite"))
    path = tmp_path / "lite.pt"
    torch.save({"model": network.state_dict(), "config": network.config.to_dict(), "model_name": "lite"}, path)
    with pytest.warns(RuntimeWarning, match="are untrained"):  # random weights: the fit is made all the same
        calibration = calibrate_weights_file(path, scenes=2)
    assert "2 procedural scenes" in calibration.fitted_on
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*untrained")  # these weights never saw a real pair
        warnings.filterwarnings("error", message=".*randomly initialised")  # but they are present
        predictor = load_model("lite", path)
    assert predictor.calibration == calibration
