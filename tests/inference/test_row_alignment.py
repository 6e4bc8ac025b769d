"""Row alignment (`inference.row_alignment`, `InferenceOptions.align_rows`): a real pair's right
image moved off the left's rows is measured from tracked corners and resampled back, so that the
network answers it as it answers the pair as it was; a pair already on its rows, or one with
nothing to track, is computed as given."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
import torch
from raw_camera import small_dev_sample

from crestereo_pp.inference import NETWORK_ONLY, InferenceOptions
from crestereo_pp.inference.row_alignment import MIN_OFFSET_PX, MIN_TRACKS, align_rows, measure_row_offset


def moved(image: np.ndarray, down_px: float, turn_deg: float = 0.0) -> np.ndarray:
    """`image` moved down by `down_px` (its content) and turned by `turn_deg` about its centre:
    bilinear, edges replicated."""
    height, width = image.shape[:2]
    warp = cv2.getRotationMatrix2D((width / 2, height / 2), turn_deg, 1.0)
    warp[1, 2] += down_px
    return cv2.warpAffine(image, warp, (width, height), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def wrong_by_over_2_px(disparity: np.ndarray, truth: np.ndarray, known: np.ndarray) -> float:
    return float(np.mean(np.abs(disparity - truth)[known] > 2.0))


def test_a_right_image_moved_down_by_a_pixel_and_a_half_is_measured_within_a_tenth():
    sample = small_dev_sample()  # Tsukuba: its own rows agree within about 0.1 px
    offset = measure_row_offset(sample.left, moved(sample.right, 1.5))
    assert offset is not None and offset.tracks >= 100
    assert offset.centre_px == pytest.approx(1.5, abs=0.1)
    assert abs(offset.across_px) < 0.2 and abs(offset.down_px) < 0.2
    as_given = measure_row_offset(sample.left, sample.right)
    assert as_given is not None and as_given.largest_px < MIN_OFFSET_PX


def test_a_turned_right_image_is_measured_as_a_tilt_across_the_rows():
    sample = small_dev_sample()
    width = sample.left.shape[1]
    offset = measure_row_offset(sample.left, moved(sample.right, 0.0, turn_deg=0.3))
    # turned counterclockwise (OpenCV's positive angle) by 0.3 degrees: the right end rises
    assert offset is not None
    assert offset.across_px == pytest.approx(-np.radians(0.3) * width, abs=0.15)
    assert abs(offset.centre_px) < 0.1


def test_tracks_in_one_part_of_the_image_are_not_carried_to_its_corners_as_tilts():
    sample = small_dev_sample()
    height, width = sample.left.shape[:2]
    down = moved(sample.right, 1.0)
    left, right = np.full_like(sample.left, 128), np.full_like(down, 128)  # texture only in one patch
    left[20:148, 200:328] = sample.left[20:148, 200:328]
    right[20:148, 170:328] = down[20:148, 170:328]
    offset = measure_row_offset(left, right)
    assert offset is not None and offset.tracks >= MIN_TRACKS
    # the plain least-squares plane of these tracks is 0.94 px off at a corner
    assert np.abs(offset.offsets(height, width) - 1.0).max() < 0.4


def test_the_network_answers_a_pair_off_its_rows_as_it_answers_the_pair_on_them(lite):
    sample = small_dev_sample()
    known = sample.valid & np.isfinite(sample.disparity)
    off = moved(sample.right, 2.0)
    on_rows = lite.predict(sample.left, sample.right, **NETWORK_ONLY).disparity
    off_rows = lite.predict(sample.left, off, **NETWORK_ONLY).disparity
    aligned = lite.predict(sample.left, off, **{**NETWORK_ONLY, "align_rows": True}).disparity
    error_on_rows = wrong_by_over_2_px(on_rows, sample.disparity, known)
    assert wrong_by_over_2_px(off_rows, sample.disparity, known) > 2 * error_on_rows
    assert wrong_by_over_2_px(aligned, sample.disparity, known) < error_on_rows + 0.01


def test_a_pair_on_its_rows_or_without_texture_is_computed_as_given():
    sample = small_dev_sample()
    as_given, offset = align_rows(sample.left, sample.right)
    assert as_given is sample.right and offset is not None and not offset.aligned
    flat = np.full((64, 96, 3), 90, np.uint8)
    assert measure_row_offset(flat, flat) is None
    assert align_rows(flat, flat) == (flat, None)


def test_a_pair_too_few_rows_tall_to_track_is_not_measured_nor_resampled():
    # A strip of noise on its rows, 5 px apart: tracked, its 16 to 40 rows gave planes up to 0.6 px off.
    for height in (16, 32, 40):
        strip = np.random.default_rng(1).integers(0, 256, (height, 4005, 3), dtype=np.uint8)
        left, right = strip[:, 5:], strip[:, :-5]
        assert measure_row_offset(left, right) is None
        assert align_rows(left, right)[0] is right


def test_each_pair_computed_carries_its_measured_row_offset_where_rows_are_aligned(lite):
    sample = small_dev_sample()
    flat = np.full((64, 96, 3), 90, np.uint8)
    lefts, rights = [sample.left, flat, sample.left], [moved(sample.right, 1.5), flat, sample.right]
    options = InferenceOptions(two_pass=False, **{**NETWORK_ONLY, "align_rows": True})
    off, untextured, on_rows = lite.predict_pairs(lefts, rights, options).row_offsets
    assert off is not None and off.aligned and off.centre_px == pytest.approx(1.5, abs=0.1)
    assert untextured is None
    assert on_rows is not None and not on_rows.aligned and on_rows.largest_px < MIN_OFFSET_PX
    assert lite.predict_pairs(lefts, rights, replace(options, align_rows=False)).row_offsets == ()


def test_an_array_keeps_its_type_and_channels_and_a_tensor_is_computed_as_given(lite):
    sample = small_dev_sample()
    off = moved(sample.right, 1.0)
    as_uint16, _ = align_rows(sample.left, off.astype(np.uint16) * 257)
    assert as_uint16.dtype == np.uint16 and as_uint16.shape == off.shape
    as_uint8, _ = align_rows(sample.left, off)
    np.testing.assert_allclose(as_uint16 / 257, as_uint8, atol=1.0)
    as_int64, _ = align_rows(sample.left, off.astype(np.int64))  # OpenCV resamples no int64: float32, same values
    assert as_int64.dtype == np.float32
    np.testing.assert_allclose(as_int64, as_uint8, atol=1.0)
    grey, _ = align_rows(sample.left, off[..., :1])
    assert grey.shape == (*off.shape[:2], 1)
    as_tensors = [torch.from_numpy(image).permute(2, 0, 1)[None].float() for image in (sample.left, off)]
    on_device = lite.predict(*as_tensors, two_pass=False, **NETWORK_ONLY).disparity[0].numpy()
    given = lite.predict(*as_tensors, two_pass=False, refine_edges=False, blend_sgbm=False).disparity[0].numpy()
    np.testing.assert_array_equal(given, on_device)  # no alignment for tensors: nothing leaves the device
