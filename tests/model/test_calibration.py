"""What the served uncertainty means: the paper's U mapped to P(error > 2 px)."""

import warnings

import numpy as np
import pytest
import torch

from model import load_model
from model.calibration import UncertaintyCalibration

CALIBRATION = UncertaintyCalibration(
    threshold_px=2.0, knots=(0.1, 0.3, 0.5), probabilities=(0.2, 0.4, 0.9), fitted_on="test"
)


def test_the_calibration_interpolates_between_its_points_and_is_flat_beyond():
    raw = torch.tensor([0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.9])
    expected = torch.tensor([0.2, 0.2, 0.3, 0.4, 0.65, 0.9, 0.9])
    torch.testing.assert_close(CALIBRATION.apply(raw), expected)
    assert UncertaintyCalibration.from_dict(CALIBRATION.to_dict()) == CALIBRATION


@pytest.mark.parametrize(
    "bad", [dict(knots=(0.1, 0.1, 0.5)), dict(probabilities=(0.5, 0.4, 0.9)), dict(knots=(0.1,), probabilities=(0.5,))]
)
def test_a_calibration_that_is_not_a_monotone_map_is_refused(bad):
    with pytest.raises(ValueError):
        UncertaintyCalibration(**{**CALIBRATION.to_dict(), **bad})


def test_a_calibrated_predictor_returns_probabilities_and_the_raw_u_on_request():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        predictor = load_model("lite", weights=None)
    rng = np.random.default_rng(0)
    left, right = (rng.integers(0, 256, (64, 96, 3), dtype=np.uint8) for _ in range(2))
    raw = predictor.predict(left, right, iters=(1, 1, 1), raw_uncertainty=True).uncertainty
    predictor.calibration = CALIBRATION  # whatever the loaded weights carried
    calibrated = predictor.predict(left, right, iters=(1, 1, 1))
    np.testing.assert_allclose(calibrated.uncertainty, CALIBRATION.apply(torch.from_numpy(raw)).numpy(), atol=1e-6)
    np.testing.assert_array_equal(
        predictor.predict(left, right, iters=(1, 1, 1), raw_uncertainty=True).uncertainty, raw
    )
