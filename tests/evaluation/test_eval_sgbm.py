"""The SGBM baseline: hole filling and the left-right check (its settings: tests/inference/test_sgbm_blend.py;
its numbers: tests/cli)."""

import numpy as np

from crestereo_pp.evaluation.sgbm import fill_invalid_from_left, sgbm_disparity


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


def test_a_pair_too_narrow_for_sgbm_gets_zeros_it_does_not_trust():
    rng = np.random.default_rng(2)
    image = rng.integers(0, 256, (32, 12, 3), dtype=np.uint8)
    disparity, consistency = sgbm_disparity(image, image, max_disparity=20)
    assert (disparity == 0).all() and np.isinf(consistency).all()
