"""OpenCV's semi-global matcher (SGBM), and the network's answer blended with it where the two
agree (``InferenceOptions.blend_sgbm``).

The network and a classical matcher fail in different ways: the network's errors of 1-4 px are
spread over whole surfaces (a precision limit in its 1/4-resolution pixels), SGBM is precise where
texture is strong and wrong or silent elsewhere. Where SGBM has an answer (its uniqueness and
speckle checks pass) within ``BLEND_WITHIN_PX`` of the network's, their mean is kept (it averages
out the two estimates' independent errors; when one of them is right, the mean is off by under
``BLEND_WITHIN_PX / 2``); elsewhere the network's answer stands as it was. A served pixel moves by
at most ``BLEND_WITHIN_PX / 2``. The uncertainty served is the network's answer's (the model
card, "Blended with SGBM", measures how it holds).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch
from torch import Tensor

from .prediction import as_image_batch

BLEND_WITHIN_PX = 4.0
"""The network's answer and SGBM's are averaged where they are within this many pixels of each
other. The fewest errors over 2 px of 1, 2, 3, 4 and 6 px on procedural validation scenes (40
plain, 24 with rooms, flat surfaces and thin structures), where no real pair has a say; the dev
pairs, looked at first, had put it at 4 of 2, 3 and 4 too (the model card, "Blended with SGBM")."""

SGBM_BLOCK_SIZE = 5
"""SGBM's matching window, px (odd)."""


def sgbm_num_disparities(max_disparity: float, width: int) -> int:
    """SGBM's search range for disparities up to `max_disparity` px in an image `width` px wide:
    `max_disparity` rounded up to a multiple of 16, at least 16, and below `width` (OpenCV's SGBM
    fails, or crashes the process, on a range as wide as the image). 0 where `width` holds no
    range of 16 (17 px or less): such an image cannot be matched."""
    widest = 16 * ((width - 1) // 16)
    return min(max(16, int(math.ceil(max_disparity / 16.0)) * 16), widest)


def create_sgbm(num_disparities: int) -> cv2.StereoSGBM:
    """A StereoSGBM matcher searching 0..`num_disparities` px (a positive multiple of 16,
    ``sgbm_num_disparities``): 5x5 windows, P1 600 and P2 2400 (8 and 32 x 3 channels x 5^2),
    disp12MaxDiff 1, uniquenessRatio 10, speckleWindowSize 100, speckleRange 2, SGBM_3WAY (the
    stereo-dev README's baseline settings)."""
    if num_disparities < 16 or num_disparities % 16:
        raise ValueError(f"SGBM searches a positive multiple of 16 px, got {num_disparities}")
    return cv2.StereoSGBM.create(
        minDisparity=0,
        numDisparities=num_disparities,
        blockSize=SGBM_BLOCK_SIZE,
        P1=8 * 3 * SGBM_BLOCK_SIZE**2,
        P2=32 * 3 * SGBM_BLOCK_SIZE**2,
        disp12MaxDiff=1,
        uniquenessRatio=10,
        speckleWindowSize=100,
        speckleRange=2,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )


def sgbm_search_range(disparity: np.ndarray) -> float:
    """How far SGBM searches to check `disparity` (px, HxW, the network's answer): a fifth beyond
    its 99.9th percentile, and 8 px more (a few wild pixels do not widen the search, which costs
    time in proportion)."""
    return 1.2 * float(np.percentile(disparity, 99.9)) + 8.0


def blend_with_sgbm(disparity: np.ndarray, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """The network's answer of one pair blended with SGBM's (see the module): `disparity` (HxW
    float32, px, positive), `left` and `right` HxWx3 uint8 RGB (``host_rgb8``). Returns the blended
    HxW float32 disparity; the answer unchanged where the image is too narrow for SGBM
    (``sgbm_num_disparities``) or the answer holds a NaN or an infinity (no range to search). Host
    work: OpenCV computes on the CPU."""
    search = sgbm_search_range(disparity)
    if not math.isfinite(search):
        return disparity
    num_disparities = sgbm_num_disparities(search, disparity.shape[1])
    if num_disparities == 0:
        return disparity
    raw = create_sgbm(num_disparities).compute(left, right)
    matched = raw.astype(np.float32) / 16.0
    agree = (raw >= 0) & (np.abs(matched - disparity) < BLEND_WITHIN_PX)
    return np.where(agree, 0.5 * (matched + disparity), disparity).astype(np.float32)


def host_rgb8(image: np.ndarray | Tensor) -> np.ndarray:
    """An image as ``as_image_batch`` reads it (an array, or a (1, 3|1, H, W) tensor on any
    device), as the HxWx3 uint8 RGB array on the host that SGBM matches (rounded, clipped)."""
    pixels = as_image_batch(image, torch.device("cpu"))[0]
    return np.ascontiguousarray(pixels.round().clamp(0, 255).to(torch.uint8).permute(1, 2, 0).numpy())
