"""What the served uncertainty means: the paper's U mapped to P(error > 2 px)."""

import warnings

import numpy as np
import pytest
import torch

from crestereo_pp.evaluation.metrics import sparsification
from crestereo_pp.inference import load_model
from crestereo_pp.inference.uncertainty_calibration import (
    ANSWER_FEATURES,
    FEATURES,
    MATCH_FEATURES,
    UncertaintyCalibration,
    answer_features,
    confidence_features,
    match_features,
)
from crestereo_pp.stereo_data.readers import StereoSample, open_dataset
from shared_data import SMALL_STEREO_DEV_PAIR, STEREO_DEV

CALIBRATION = UncertaintyCalibration(
    threshold_px=2.0, knots=(0.1, 0.3, 0.5), probabilities=(0.2, 0.4, 0.9), fitted_on="test"
)


def test_the_calibration_interpolates_between_its_points_and_is_flat_beyond():
    raw = torch.tensor([0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.9])
    expected = torch.tensor([0.2, 0.2, 0.3, 0.4, 0.65, 0.9, 0.9])
    torch.testing.assert_close(CALIBRATION.probability(raw), expected)
    assert UncertaintyCalibration.from_dict(CALIBRATION.to_dict()) == CALIBRATION


def test_a_calibration_without_features_scores_by_u_alone_as_files_fitted_before_them():
    old_file = {"threshold_px": 2.0, "knots": [0.1, 0.3, 0.5], "probabilities": [0.2, 0.4, 0.9], "fitted_on": "old"}
    calibration = UncertaintyCalibration.from_dict(old_file)
    raw = torch.rand(1, 1, 8, 12) * 0.5
    disparity, left, right = torch.rand(1, 1, 8, 12) * 5, torch.rand(1, 3, 8, 12) * 255, torch.rand(1, 3, 8, 12) * 255
    torch.testing.assert_close(calibration.apply(raw, disparity, left, right), calibration.probability(raw))


def test_a_calibration_fitted_before_the_match_features_scores_by_the_first_six_as_before():
    rng = np.random.default_rng(1)
    six = len(ANSWER_FEATURES)
    before = UncertaintyCalibration(
        threshold_px=2.0,
        knots=(-1.0, 1.0),
        probabilities=(0.1, 0.6),
        fitted_on="before the match features",
        feature_mean=tuple(rng.random(six)),
        feature_scale=tuple(rng.random(six) + 0.5),
        coefficients=tuple(rng.normal(size=2 * six + 1)),
    )
    raw, disparity = torch.rand(1, 1, 16, 24) * 0.5, torch.rand(1, 1, 16, 24) * 5
    left, right = torch.rand(1, 3, 16, 24) * 255, torch.rand(1, 3, 16, 24) * 255
    answer = answer_features(raw, disparity, left)
    torch.testing.assert_close(before.score(raw, disparity, left, right), before.feature_score(answer))
    assert UncertaintyCalibration.from_dict(before.to_dict()) == before


def test_the_features_see_depth_edges_texture_and_matches_outside_the_right_image():
    disparity = torch.full((1, 1, 32, 48), 4.0)
    disparity[..., 24:] = 12.0  # a depth edge at x = 24
    left = torch.zeros(1, 3, 32, 48)
    left[..., :12] = torch.rand(1, 3, 32, 12) * 255  # texture on the left only
    maps = confidence_features(torch.zeros(1, 1, 32, 48), disparity, left, left)
    features = dict(zip(FEATURES, maps[0], strict=True))
    assert features["disparity_edges"][16, 24] > 1.0 and features["disparity_edges"][16, 40] == pytest.approx(
        0.0, abs=1e-5
    )
    assert features["texture"][16, 4] > 5.0 and features["texture"][16, 36] == 0.0
    outside = features["outside_right_view"][16]
    assert outside[:4].tolist() == [1.0] * 4 and outside[4:].sum() == 0.0  # x - 4 < 0 for x < 4 only
    assert features["log_disparity"][16, 40] == pytest.approx(np.log1p(12.0))


@pytest.mark.skipif(not STEREO_DEV.is_dir(), reason=f"no real stereo pairs at {STEREO_DEV}")
def test_the_match_features_tell_the_true_disparity_of_a_real_pair_from_one_a_few_pixels_off():
    sample = _dev_pair(SMALL_STEREO_DEV_PAIR)
    left, right = (torch.from_numpy(image).permute(2, 0, 1)[None].float() for image in (sample.left, sample.right))
    true = torch.from_numpy(np.where(sample.valid, sample.disparity, 0.0)).float()[None, None]
    inside = torch.from_numpy(sample.valid & (sample.disparity > 4))  # the shifted match stays in the image
    textured = answer_features(torch.zeros_like(true), true, left)[0, ANSWER_FEATURES.index("texture")] > 4.0
    kept = inside & textured
    for name, at_truth, off_by_3 in zip(
        MATCH_FEATURES, match_features(true, left, right)[0], match_features(true - 3.0, left, right)[0], strict=True
    ):
        # the right image matches the left at the truth, not 3 px off (where a better match lies nearby)
        assert at_truth[kept].median() < off_by_3[kept].median() - 0.2, name
    dissimilarity = match_features(true, left, right)[0, 0]
    assert dissimilarity[kept].median() < 0.2  # the windows agree where the ground truth matches them


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
    np.testing.assert_allclose(
        calibrated.uncertainty, CALIBRATION.probability(torch.from_numpy(raw)).numpy(), atol=1e-6
    )
    np.testing.assert_array_equal(
        predictor.predict(left, right, iters=(1, 1, 1), raw_uncertainty=True).uncertainty, raw
    )


@pytest.mark.skipif(not STEREO_DEV.is_dir(), reason=f"no real stereo pairs at {STEREO_DEV}")
def test_the_shipped_uncertainty_flags_the_wrong_pixels_of_a_real_pair_far_better_than_u_alone():
    sample = _dev_pair(SMALL_STEREO_DEV_PAIR)
    predictor = load_model("lite", backend="torch", precision="fp32")
    served = predictor.predict(sample.left, sample.right)
    raw = predictor.predict(sample.left, sample.right, raw_uncertainty=True).uncertainty
    errors = np.abs(served.disparity - sample.disparity)[sample.valid]
    ranked_by_features, ranked_by_u = (sparsification(errors, m[sample.valid]) for m in (served.uncertainty, raw))
    # removing the pixels the map flags first lowers the error rate far faster than chance (1.0) or U does
    assert ranked_by_features.auc / ranked_by_features.auc_random < 0.5
    assert ranked_by_features.auc < 0.5 * ranked_by_u.auc
    observed = (errors > 2.0).mean()
    assert abs(served.uncertainty[sample.valid].mean() - observed) < 0.05  # calibrated on this pair too


def _dev_pair(name: str) -> StereoSample:
    dataset = open_dataset(STEREO_DEV)
    return next(dataset[i] for i in range(len(dataset)) if dataset[i].name == name)
