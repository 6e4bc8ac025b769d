"""OpenCV StereoSGBM baseline, with exactly the settings of the stereo-dev README's table
(``inference.sgbm.create_sgbm``: the matcher the served answers are blended with too).

numDisparities = ceil(max GT / 16) * 16 (below the image's width), blockSize 5, P1 600 (8*3*5^2),
P2 2400 (32*3*5^2), disp12MaxDiff 1, uniquenessRatio 10, speckleWindowSize 100, speckleRange 2,
SGBM_3WAY, on the colour images; disparity = output / 16; invalid outputs (< 0) filled from the
nearest valid pixel to the left (a row's leading invalid run from the nearest valid pixel to the right).
"""

from __future__ import annotations

import numpy as np

from crestereo_pp.inference.sgbm import create_sgbm, sgbm_num_disparities


def fill_invalid_from_left(disparity: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Replace each invalid pixel by the nearest valid pixel to its left in the same row.

    disparity: float HxW; valid: bool HxW. A row's leading invalid run takes the nearest valid
    pixel to its right; a row with no valid pixel becomes 0. Returns a new float32 array.
    """
    height, width = disparity.shape
    columns = np.broadcast_to(np.arange(width), (height, width))
    last_valid_left = np.maximum.accumulate(np.where(valid, columns, -1), axis=1)
    next_valid_right = np.minimum.accumulate(np.where(valid, columns, width)[:, ::-1], axis=1)[:, ::-1]
    source = np.where(last_valid_left >= 0, last_valid_left, next_valid_right)
    row_has_valid = source < width
    filled = np.take_along_axis(disparity, np.where(row_has_valid, source, 0), axis=1)
    return np.where(row_has_valid, filled, 0.0).astype(np.float32)


def sgbm_disparity(left: np.ndarray, right: np.ndarray, max_disparity: float) -> tuple[np.ndarray, np.ndarray]:
    """Baseline disparity (float32 HxW, px, positive, no holes: invalid outputs filled from the
    left) of a rectified uint8 HxWx3 pair, and its left-right consistency error as an
    uncertainty (float32 HxW, px, larger = less trusted): |d_L(x) - d_R(x - d_L(x))| with d_R the
    right view's disparity (SGBM on the mirrored, swapped pair); pixels SGBM left invalid, or
    whose match falls outside the right view or on an invalid right pixel, get +inf. An image too
    narrow for SGBM (17 px or less) gets 0 everywhere, at +inf."""
    num_disparities = sgbm_num_disparities(max_disparity, left.shape[1])
    if num_disparities == 0:
        return np.zeros(left.shape[:2], np.float32), np.full(left.shape[:2], np.inf, np.float32)
    matcher = create_sgbm(num_disparities)
    raw_left = matcher.compute(left, right)
    raw_right = matcher.compute(np.ascontiguousarray(right[:, ::-1]), np.ascontiguousarray(left[:, ::-1]))[:, ::-1]
    disparity_left = raw_left.astype(np.float32) / 16.0
    disparity_right = raw_right.astype(np.float32) / 16.0
    height, width = disparity_left.shape
    match = np.round(np.arange(width)[None, :] - disparity_left).astype(np.int64)
    inside = (raw_left >= 0) & (match >= 0) & (match < width)
    right_at_match = np.take_along_axis(disparity_right, np.clip(match, 0, width - 1), axis=1)
    right_valid = np.take_along_axis(raw_right >= 0, np.clip(match, 0, width - 1), axis=1)
    consistency = np.where(inside & right_valid, np.abs(disparity_left - right_at_match), np.inf)
    return fill_invalid_from_left(disparity_left, raw_left >= 0), consistency.astype(np.float32)
