"""Spec of `refine_edges`: the answer's depth edges put where the left image's colour edges are."""

import numpy as np
import pytest
import torch
from raw_camera import small_dev_sample

from crestereo_pp.inference import NETWORK_ONLY, depth_edges
from crestereo_pp.inference.border_strip import raise_border_strip
from crestereo_pp.inference.depth_edges import MEDIAN_RADIUS_PX, depth_edge_pixels, refine_depth_edges

NEAR, FAR = 30.0, 10.0  # px: the two sides' disparities


def two_surfaces(height: int = 48, width: int = 96) -> tuple[np.ndarray, np.ndarray]:
    """A left image whose left half is a dark textured surface and right half a light one (the
    colour edge at x = width / 2), and an answer that blurs the depth edge between them over 8 px
    (NEAR on the left, FAR on the right), as the network does."""
    noise = np.random.default_rng(0).integers(-12, 13, (height, width, 3))
    image = np.where(np.arange(width)[None, :, None] < width // 2, 60, 190) + noise
    ramp = np.clip((np.arange(width) - (width // 2 - 4)) / 8.0, 0.0, 1.0)
    answer = np.tile(NEAR + (FAR - NEAR) * ramp, (height, 1)).astype(np.float32)
    return image.astype(np.uint8), answer


def test_a_blurred_depth_edge_is_drawn_back_towards_the_colour_edge():
    image, answer = two_surfaces()
    truth = np.where(np.arange(96) < 48, NEAR, FAR)[None, :]
    middle = slice(8, -8)  # rows away from the image's top and bottom
    before = np.abs(answer - truth)[middle]
    after = np.abs(refine_depth_edges(answer, image) - truth)[middle]
    assert (after <= before).all()
    assert after.sum() < 0.5 * before.sum()  # 8 px of blur: 40 px of error a row before


def test_pixels_away_from_depth_edges_keep_their_answer():
    image, _ = two_surfaces()
    slanted = np.tile(5.0 + 0.4 * np.arange(96, dtype=np.float32), (48, 1))  # a plane: 0.4 px per px
    assert not depth_edge_pixels(slanted).any()
    np.testing.assert_array_equal(refine_depth_edges(slanted, image), slanted)


def test_each_refined_pixel_takes_one_of_its_neighbours_answers(lite):
    sample = small_dev_sample()
    left, right = sample.left[:160, :224], sample.right[:160, :224]
    answer = lite.predict(left, right, **NETWORK_ONLY).disparity
    refined = refine_depth_edges(answer, left)
    changed = refined != answer
    assert changed.any() and not (changed & ~depth_edge_pixels(answer)).any()
    r = MEDIAN_RADIUS_PX
    padded = np.pad(answer, r, mode="edge")
    nearest = np.full(answer.shape, np.inf, np.float32)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            around = padded[r + dy : r + dy + answer.shape[0], r + dx : r + dx + answer.shape[1]]
            nearest = np.minimum(nearest, np.abs(refined - around))
    np.testing.assert_array_equal(nearest, 0.0)


def test_refining_a_real_answer_gets_fewer_pixels_wrong_by_over_2_px(lite):
    sample = small_dev_sample()  # Tsukuba, with its ground truth
    known = sample.valid & np.isfinite(sample.disparity)

    def wrong_by_over_2_px(disparity: np.ndarray) -> float:
        return float(np.mean(np.abs(disparity - sample.disparity)[known] > 2.0))

    unrefined = lite.predict(sample.left, sample.right, refine_edges=False)
    refined = lite.predict(sample.left, sample.right)  # the default: blended with SGBM, then refined
    assert wrong_by_over_2_px(refined.disparity) < 0.95 * wrong_by_over_2_px(unrefined.disparity)
    np.testing.assert_array_equal(refined.uncertainty, unrefined.uncertainty)  # the network answer's


def test_an_answer_with_a_nan_is_served_as_it_is():
    image, answer = two_surfaces()
    answer[3, 4] = np.nan
    np.testing.assert_array_equal(refine_depth_edges(answer, image), answer)


@pytest.mark.parametrize(("height", "width"), [(1, 1), (1, 40), (40, 1), (2, 3), (7, 9)])
def test_tiny_images_are_refined_without_a_crash(height, width):
    image = np.random.default_rng(1).integers(0, 256, (height, width, 3), dtype=np.uint8)
    answer = np.where(np.arange(width)[None, :] < width // 2, NEAR, FAR) * np.ones((height, 1), np.float32)
    refined = refine_depth_edges(answer.astype(np.float32), image)
    assert refined.shape == (height, width) and np.isin(refined, [NEAR, FAR]).all()


def test_device_tensors_are_refined_too_and_the_maps_stay_tensors(lite):
    sample = small_dev_sample()
    left, right = (
        torch.from_numpy(x[:96, :160].copy()).permute(2, 0, 1)[None].float() for x in (sample.left, sample.right)
    )
    unrefined = lite.predict(left, right, refine_edges=False)
    refined = lite.predict(left, right)
    assert isinstance(refined.disparity, torch.Tensor) and refined.disparity.shape == (1, 96, 160)
    left = sample.left[:96, :160]
    expected = raise_border_strip(refine_depth_edges(unrefined.disparity[0].numpy(), left), left)
    np.testing.assert_array_equal(refined.disparity[0].numpy(), expected)


def test_edge_pixels_refined_a_chunk_at_a_time_give_the_answer_of_one_go(lite, monkeypatch):
    sample = small_dev_sample()
    left, right = sample.left[:160, :224], sample.right[:160, :224]
    answer = lite.predict(left, right, **NETWORK_ONLY).disparity
    in_one_go = refine_depth_edges(answer, left)
    monkeypatch.setattr(depth_edges, "EDGE_PIXELS_PER_CHUNK", 250)  # chunks ending mid-row, a short last one
    assert depth_edge_pixels(answer).sum() > 500
    np.testing.assert_array_equal(refine_depth_edges(answer, left), in_one_go)
