"""Fitting the meaning of the uncertainty for a set of weights, on procedural scenes."""

import warnings

import numpy as np
import pytest
import torch

from model import CREStereoPP, ModelConfig, load_model
from training.calibrate import calibrate_weights_file, fit_calibration


def test_the_fit_recovers_a_known_error_probability_and_is_monotone():
    rng = np.random.default_rng(0)
    raw = rng.random(50_000) * 0.5
    truth = 0.1 + 1.6 * raw  # P(error > 2 px) rises from 0.1 to 0.9 with U
    errors = np.where(rng.random(raw.size) < truth, 4.0, 0.5)
    calibration = fit_calibration(raw, errors, 2.0, "test", bins=16)
    assert all(b > a for a, b in zip(calibration.probabilities, calibration.probabilities[1:], strict=False))
    fitted = calibration.apply(torch.tensor([0.05, 0.25, 0.45], dtype=torch.float64)).numpy()
    np.testing.assert_allclose(fitted, [0.18, 0.5, 0.82], atol=0.05)


def test_equal_uncertainties_cannot_be_calibrated():
    with pytest.raises(ValueError, match="all equal"):
        fit_calibration(np.full(100, 0.5), np.zeros(100), 2.0, "test", bins=8)


def test_calibrating_a_weights_file_stores_a_fit_that_load_model_applies(tmp_path):
    torch.manual_seed(0)
    network = CREStereoPP(ModelConfig.preset("lite"))
    path = tmp_path / "lite.pt"
    torch.save({"model": network.state_dict(), "config": network.config.to_dict(), "model_name": "lite"}, path)
    calibration = calibrate_weights_file(path, scenes=2)
    assert "2 procedural scenes" in calibration.fitted_on
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*untrained")  # these weights never saw a real pair
        warnings.filterwarnings("error", message=".*randomly initialised")  # but they are present
        predictor = load_model("lite", path)
    assert predictor.calibration == calibration
