"""Spec of `refine_edges`' last step: the strip along the left image's left edge, whose matches fall
outside the right image, raised towards the surface beside it."""

import numpy as np
import pytest
from raw_camera import dev_sample

from crestereo_pp.inference import NETWORK_ONLY
from crestereo_pp.inference.border_strip import STRIP_RAISE_PX, raise_border_strip, strip_ends

SURFACE = 20.0  # px: the disparity of a fronto-parallel surface reaching the left edge


def drifting_answer(height: int = 8, width: int = 64) -> np.ndarray:
    """The network's kind of answer on a surface at SURFACE px reaching the left edge: right where
    the matches stay inside the right image, falling 0.5 px per px towards the left edge in the
    strip (x < SURFACE), as the network's extrapolation falls short."""
    x = np.arange(width, dtype=np.float32)
    row = np.where(x < SURFACE, SURFACE - 0.5 * (SURFACE - x), SURFACE)
    return np.tile(row, (height, 1)).astype(np.float32)


def grey(height: int = 8, width: int = 64) -> np.ndarray:
    """A left image of one colour: one surface."""
    return np.full((height, width, 3), 128, np.uint8)


def test_the_strip_is_where_matches_fall_left_of_the_right_image():
    answer = drifting_answer()
    ends = strip_ends(answer)
    x = np.arange(answer.shape[1])
    assert (ends == 20).all()  # 20 - 20 = 0: the first pixel whose match is inside
    assert (x[None, :20] - answer[:, :20] < 0).all()


def test_a_drifting_strip_on_one_surface_is_raised_towards_it_by_at_most_the_bound():
    answer = drifting_answer()
    raised = raise_border_strip(answer, grey())
    np.testing.assert_allclose(raised, np.minimum(SURFACE, answer + STRIP_RAISE_PX))
    assert np.abs(raised - SURFACE).sum() < 0.5 * np.abs(answer - SURFACE).sum()
    np.testing.assert_array_equal(raised[:, 20:], answer[:, 20:])  # right of the strip: untouched


def test_strip_pixels_of_another_colour_are_raised_less():
    answer, image = drifting_answer(), grey()
    image[:, :6] = (200, 40, 40)  # a red object in the strip, the grey surface beside it
    raise_by = raise_border_strip(answer, image) - answer
    assert (raise_by[:, :6] < 0.1 * raise_by[:, 6:10].min()).all()


def test_a_nearer_object_in_the_strip_is_never_lowered():
    answer = drifting_answer()
    answer[:, 2:6] = 35.0  # something nearer, seen by the network in the strip
    np.testing.assert_array_equal(raise_border_strip(answer, grey())[:, 2:6], 35.0)


def test_rows_without_a_match_inside_and_nan_answers_keep_theirs():
    answer = drifting_answer()
    answer[0] = 100.0  # x - d < 0 across the whole row: nothing to raise it towards
    answer[1, 3] = np.nan
    raised = raise_border_strip(answer, grey())
    np.testing.assert_array_equal(raised[0], answer[0])
    assert np.isnan(raised[1, 3]) and np.isfinite(np.delete(raised[1], 3)).all()


@pytest.mark.parametrize(("height", "width"), [(1, 1), (1, 40), (40, 1), (2, 3)])
def test_tiny_answers_are_handled(height, width):
    answer = np.full((height, width), 5.0, np.float32)
    image = np.random.default_rng(2).integers(0, 256, (height, width, 3), dtype=np.uint8)
    raised = raise_border_strip(answer, image)
    assert raised.shape == (height, width) and raised.dtype == np.float32
    assert (raised >= answer).all() and (raised <= answer + STRIP_RAISE_PX).all()


def test_on_a_real_driving_pair_the_strip_gets_fewer_pixels_wrong(lite):
    sample = dev_sample("kitti2015_000001_10")
    columns = slice(0, 320)  # the left of the pair: the strip, and the road and cars beside it
    left, right, truth = sample.left[:, columns], sample.right[:, columns], sample.disparity[:, columns]
    answer = lite.predict(left, right, **NETWORK_ONLY).disparity
    raised = raise_border_strip(answer, left)
    strip = np.arange(320)[None, :] < strip_ends(answer)[:, None]
    known = strip & sample.valid[:, columns] & np.isfinite(truth)
    assert known.sum() > 500  # KITTI's truth is sparse: about a thousand strip pixels here

    def wrong_by_over_2_px(disparity: np.ndarray) -> int:
        return int((np.abs(disparity - truth)[known] > 2.0).sum())

    assert wrong_by_over_2_px(raised) < 0.85 * wrong_by_over_2_px(answer)
    assert np.abs(raised - truth)[known].sum() < np.abs(answer - truth)[known].sum()
    np.testing.assert_array_equal(raised[~strip], answer[~strip])
