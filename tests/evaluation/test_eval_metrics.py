"""Metrics against values computed by hand on tiny maps."""

import math

import numpy as np
import pytest

from crestereo_pp.evaluation.metrics import DisparityMetrics, compute_metrics, mean_metrics, reliability, sparsification

INF = np.inf


def test_metrics_of_a_hand_made_map():
    # errors on the 5 valid pixels: 0.5, 1.5, 2.5, 3.5, 10.0 (the inf and the masked pixel never count)
    ground_truth = np.array([[10.0, 10.0, 10.0, 100.0], [100.0, 20.0, INF, 5.0]], np.float32)
    prediction = np.array([[10.5, 8.5, 12.5, 96.5], [90.0, 0.0, 3.0, 5.0]], np.float32)
    valid = np.array([[True, True, True, True], [True, False, True, False]])

    m = compute_metrics(prediction, ground_truth, valid)

    assert m.valid_pixels == 5
    assert m.epe == pytest.approx((0.5 + 1.5 + 2.5 + 3.5 + 10.0) / 5)
    assert m.bad1 == pytest.approx(100 * 4 / 5)  # 1.5, 2.5, 3.5, 10
    assert m.bad2 == pytest.approx(100 * 3 / 5)  # 2.5, 3.5, 10
    assert m.bad3 == pytest.approx(100 * 2 / 5)  # 3.5, 10
    # D1: > 3 px AND > 5 %: 3.5 px at gt 100 is 3.5 % (not an outlier); 10 px at gt 100 is 10 %
    assert m.d1_all == pytest.approx(100 * 1 / 5)


def test_an_error_equal_to_the_threshold_is_not_bad():
    ground_truth = np.zeros((1, 3), np.float32) + 10
    prediction = np.array([[11.0, 12.0, 13.0]], np.float32)
    m = compute_metrics(prediction, ground_truth, np.ones((1, 3), bool))
    assert (m.bad1, m.bad2, m.bad3) == pytest.approx((100 * 2 / 3, 100 * 1 / 3, 0.0))


def test_d1_needs_both_more_than_3_px_and_more_than_5_percent():
    ground_truth = np.array([[40.0, 80.0, 200.0]], np.float32)
    prediction = np.array([[44.0, 83.9, 209.0]], np.float32)  # 4 px = 10 %; 3.9 px = 4.9 %; 9 px = 4.5 %
    m = compute_metrics(prediction, ground_truth, np.ones((1, 3), bool))
    assert m.d1_all == pytest.approx(100 / 3)


def test_no_valid_pixel_gives_nan_not_a_crash():
    m = compute_metrics(np.zeros((2, 2), np.float32), np.full((2, 2), INF, np.float32), np.zeros((2, 2), bool))
    assert m.valid_pixels == 0 and math.isnan(m.epe) and math.isnan(m.bad2)


def test_shape_mismatch_is_an_error():
    with pytest.raises(ValueError, match="shapes differ"):
        compute_metrics(np.zeros((2, 3)), np.zeros((3, 2)), np.ones((3, 2), bool))


def test_mean_over_pairs_weights_every_pair_equally():
    small = DisparityMetrics(epe=1.0, bad1=10.0, bad2=4.0, bad3=2.0, d1_all=1.0, valid_pixels=10)
    large = DisparityMetrics(epe=3.0, bad1=30.0, bad2=8.0, bad3=6.0, d1_all=3.0, valid_pixels=1000)
    mean = mean_metrics([small, large])
    assert (mean.epe, mean.bad1, mean.bad2, mean.bad3, mean.d1_all) == (2.0, 20.0, 6.0, 4.0, 2.0)
    assert mean.valid_pixels == 1010


def test_a_perfect_ranking_reaches_the_optimal_sparsification_area_and_a_random_one_the_error_rate():
    rng = np.random.default_rng(0)
    errors = np.where(rng.random(100_000) < 0.3, 5.0, 0.5)  # 30 % bad-2
    perfect = sparsification(errors, errors + rng.random(errors.size) * 0.1)
    random = sparsification(errors, rng.random(errors.size))
    assert perfect.auc_random == pytest.approx(0.3, abs=0.01)
    assert perfect.auc_optimal == pytest.approx(0.3 + 0.7 * math.log(0.7), rel=1e-2)
    assert perfect.auc == pytest.approx(perfect.auc_optimal, abs=1e-3)
    assert perfect.ratio_to_optimal == pytest.approx(1.0, abs=0.02)
    assert random.auc == pytest.approx(0.3, abs=0.01)
    assert perfect.bad_percent[0] == random.bad_percent[0] == pytest.approx(30, abs=1)
    at = dict(zip(perfect.removed_percent, perfect.bad_percent, strict=True))
    assert at[30.0] == pytest.approx(0.0, abs=0.1) and at[15.0] == pytest.approx(100 * 0.15 / 0.85, abs=0.5)
    assert perfect.removed_percent == tuple(float(r) for r in range(0, 100, 5))


def test_an_inverted_ranking_is_worse_than_random():
    errors = np.linspace(0, 4, 1000)
    inverted = sparsification(errors, -errors)
    assert inverted.auc > inverted.auc_random > inverted.auc_optimal


def test_probabilities_that_match_the_error_frequency_have_a_small_calibration_error():
    rng = np.random.default_rng(1)
    probability = rng.random(200_000)
    errors = np.where(rng.random(probability.size) < probability, 5.0, 0.0)  # P(bad) = probability
    calibrated = reliability(errors, probability, threshold_px=2.0)
    overconfident = reliability(errors, probability * 0.2, threshold_px=2.0)
    assert calibrated.expected_calibration_error < 0.01
    assert overconfident.expected_calibration_error > 0.3
    assert sum(calibrated.pixels) == probability.size
    for predicted, observed in zip(calibrated.predicted, calibrated.observed, strict=True):
        assert observed == pytest.approx(predicted, abs=0.02)
    assert math.isnan(overconfident.observed[-1])  # no prediction above 0.2: empty bins
