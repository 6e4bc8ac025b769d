"""The SGBM baseline: the stereo-dev README's settings and hole filling (its numbers: tests/cli)."""

import numpy as np
import pytest

from crestereo_pp.evaluation.sgbm import create_sgbm, fill_invalid_from_left, sgbm_disparity, sgbm_num_disparities


@pytest.mark.parametrize(("max_disparity", "expected"), [(14.0, 16), (16.0, 16), (52.75, 64), (152.12, 160), (0.0, 16)])
def test_disparity_range_is_the_ground_truth_maximum_rounded_up_to_16(max_disparity, expected):
    assert sgbm_num_disparities(max_disparity) == expected


def test_matcher_has_the_readme_settings():
    sgbm = create_sgbm(100.5)
    assert (sgbm.getNumDisparities(), sgbm.getBlockSize(), sgbm.getP1(), sgbm.getP2()) == (112, 5, 600, 2400)
    assert (sgbm.getDisp12MaxDiff(), sgbm.getUniquenessRatio()) == (1, 10)
    assert (sgbm.getSpeckleWindowSize(), sgbm.getSpeckleRange(), sgbm.getMode()) == (100, 2, 2)  # 2 = SGBM_3WAY


def test_holes_take_the_nearest_valid_value_on_their_left_and_leading_holes_the_right():
    disparity = np.array([[9, 1, 9, 9, 2, 9], [9, 9, 3, 9, 9, 4], [9, 9, 9, 9, 9, 9]], np.float32)
    valid = np.array([[0, 1, 0, 0, 1, 0], [0, 0, 1, 0, 0, 1], [0, 0, 0, 0, 0, 0]], bool)
    filled = fill_invalid_from_left(disparity, valid)
    np.testing.assert_array_equal(filled, [[1, 1, 1, 1, 2, 2], [3, 3, 3, 3, 3, 4], [0, 0, 0, 0, 0, 0]])


def test_sgbm_finds_a_constant_shift_on_a_textured_pair():
    rng = np.random.default_rng(0)
    right = rng.integers(0, 256, (64, 128, 3), dtype=np.uint8)
    left = np.roll(right, 7, axis=1)  # left(x) = right(x - 7): disparity 7
    disparity, consistency = sgbm_disparity(left, right, max_disparity=20)
    assert disparity.dtype == np.float32 and np.isfinite(disparity).all()
    assert np.median(np.abs(disparity[:, 30:] - 7.0)) < 0.25
    assert np.median(consistency[:, 30:]) < 0.5  # both views agree where the match is seen


def test_sgbm_left_right_consistency_flags_where_the_views_disagree():
    rng = np.random.default_rng(1)
    right = rng.integers(0, 256, (64, 128, 3), dtype=np.uint8)
    left = np.roll(right, 7, axis=1)
    left[:, 60:80] = rng.integers(0, 256, (64, 20, 3), dtype=np.uint8)  # a patch seen by the left view only
    disparity, consistency = sgbm_disparity(left, right, max_disparity=20)
    inconsistent = ~(consistency < 1.0)
    assert inconsistent[:, 62:78].mean() > 3 * inconsistent[:, 30:55].mean()
    assert np.isinf(consistency[:, :7]).all()  # matches left of the right view's frame
