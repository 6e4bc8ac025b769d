"""Spec of `blend_sgbm`: the network's answer averaged with OpenCV's SGBM where the two agree."""

import numpy as np
import pytest
import torch
from raw_camera import small_dev_sample

from crestereo_pp.inference import NETWORK_ONLY
from crestereo_pp.inference.sgbm import (
    BLEND_WITHIN_PX,
    blend_with_sgbm,
    create_sgbm,
    host_rgb8,
    sgbm_num_disparities,
)

SHIFT = 7  # px: the textured pair's disparity


def shifted_pair(height: int = 64, width: int = 128) -> tuple[np.ndarray, np.ndarray]:
    """A random texture and the same shifted SHIFT px: left(x) = right(x - SHIFT)."""
    right = np.random.default_rng(0).integers(0, 256, (height, width, 3), dtype=np.uint8)
    return np.roll(right, SHIFT, axis=1), right


@pytest.mark.parametrize(
    ("max_disparity", "width", "expected"),
    [(14.0, 640, 16), (16.0, 640, 16), (52.75, 640, 64), (152.12, 640, 160), (0.0, 640, 16), (300.0, 200, 192)],
)
def test_the_search_range_is_the_largest_disparity_rounded_up_to_16_and_below_the_width(max_disparity, width, expected):
    assert sgbm_num_disparities(max_disparity, width) == expected


@pytest.mark.parametrize("width", [1, 8, 16])
def test_an_image_of_16_px_or_less_has_no_search_range(width):
    assert sgbm_num_disparities(10.0, width) == 0


def test_the_matcher_has_the_baseline_settings():
    sgbm = create_sgbm(112)
    assert (sgbm.getNumDisparities(), sgbm.getBlockSize(), sgbm.getP1(), sgbm.getP2()) == (112, 5, 600, 2400)
    assert (sgbm.getDisp12MaxDiff(), sgbm.getUniquenessRatio()) == (1, 10)
    assert (sgbm.getSpeckleWindowSize(), sgbm.getSpeckleRange(), sgbm.getMode()) == (100, 2, 2)  # 2 = SGBM_3WAY
    with pytest.raises(ValueError, match="multiple of 16"):
        create_sgbm(100)


def test_where_sgbm_agrees_the_mean_is_served_and_where_it_does_not_the_network_answer_stands():
    left, right = shifted_pair()
    answer = np.full((64, 128), SHIFT + 1.0, np.float32)  # 1 px off: SGBM agrees, the mean is nearer
    answer[:, 64:] = SHIFT + BLEND_WITHIN_PX + 3.0  # 7 px off: SGBM disagrees
    blended = blend_with_sgbm(answer, left, right)
    seen = blended[8:-8, 16:60]  # where the match is in the right view, away from the borders
    assert np.median(seen) == pytest.approx(SHIFT + 0.5, abs=0.1)
    np.testing.assert_array_equal(blended[:, 64:], SHIFT + BLEND_WITHIN_PX + 3.0)
    assert np.abs(blended - answer).max() <= BLEND_WITHIN_PX / 2


@pytest.mark.parametrize("width", [5, 16, 17, 40])
def test_images_too_narrow_for_the_search_are_answered_without_a_crash(width):
    # OpenCV's SGBM crashes the process on a search as wide as the image; the range is kept below it
    left, right = shifted_pair(32, width)
    answer = np.full((32, width), 30.0, np.float32)
    blended = blend_with_sgbm(answer, left, right)
    assert blended.shape == answer.shape and np.isfinite(blended).all()
    if width <= 16:
        np.testing.assert_array_equal(blended, answer)


def test_the_blend_moves_a_real_answer_by_at_most_half_the_agreement_and_can_be_turned_off(lite):
    sample = small_dev_sample()
    left, right = sample.left[:192, :256], sample.right[:192, :256]
    own = lite.predict(left, right, **NETWORK_ONLY)
    blended = lite.predict(left, right, refine_edges=False)
    moved = np.abs(blended.disparity - own.disparity)
    assert 0 < moved.max() <= BLEND_WITHIN_PX / 2 + 1e-4
    np.testing.assert_array_equal(blended.uncertainty, own.uncertainty)  # the network answer's


def test_pairs_of_different_sizes_in_one_batch_are_blended_each_as_alone(lite):
    sample = small_dev_sample()
    # one padded shape (192x256): one batch, the smaller pair padded in it
    pairs = [(sample.left[:180, :230], sample.right[:180, :230]), (sample.left[:192, :256], sample.right[:192, :256])]
    together = lite.predict_batch([p[0] for p in pairs], [p[1] for p in pairs], two_pass=False)
    for (left, right), batched in zip(pairs, together, strict=True):
        alone = lite.predict(left, right, two_pass=False)
        assert np.mean(np.abs(batched.disparity - alone.disparity) < 1e-3) > 0.999


def test_the_blend_gets_fewer_pixels_of_a_real_pair_wrong_by_over_1_px(lite):
    sample = small_dev_sample()  # Tsukuba, with its ground truth
    known = sample.valid & np.isfinite(sample.disparity)

    def wrong_by_over_1_px(disparity: np.ndarray) -> float:
        return float(np.mean(np.abs(disparity - sample.disparity)[known] > 1.0))

    own = lite.predict(sample.left, sample.right, **NETWORK_ONLY).disparity
    blended = lite.predict(sample.left, sample.right, refine_edges=False).disparity
    assert wrong_by_over_1_px(blended) < 0.9 * wrong_by_over_1_px(own)


def test_an_answer_with_a_nan_is_served_as_it_is():
    left, right = shifted_pair()
    answer = np.full((64, 128), float(SHIFT), np.float32)
    answer[3, 4] = np.nan
    np.testing.assert_array_equal(blend_with_sgbm(answer, left, right), answer)


def test_grey_16_bit_and_tensor_images_are_matched_as_the_network_reads_them():
    left, right = shifted_pair()
    grey16 = (left[..., 0].astype(np.uint16) * 257)[..., None]
    np.testing.assert_array_equal(host_rgb8(grey16), np.repeat(left[..., :1], 3, axis=2))
    tensor = torch.from_numpy(left).permute(2, 0, 1)[None].float()
    np.testing.assert_array_equal(host_rgb8(tensor), left)


def test_device_tensors_are_blended_too_and_the_maps_stay_tensors(lite):
    sample = small_dev_sample()
    left, right = (
        torch.from_numpy(x[:96, :160].copy()).permute(2, 0, 1)[None].float() for x in (sample.left, sample.right)
    )
    own = lite.predict(left, right, **NETWORK_ONLY)
    blended = lite.predict(left, right, refine_edges=False)
    assert isinstance(blended.disparity, torch.Tensor) and blended.disparity.shape == (1, 96, 160)
    moved = (blended.disparity - own.disparity).abs()
    assert 0 < float(moved.max()) <= BLEND_WITHIN_PX / 2 + 1e-4
