"""Result encodings: the colour preview and its scales."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from crestereo_pp.service.api.response_bodies import encode_preview
from crestereo_pp.stereo_data.visualize import BAR_HEIGHT, PREVIEW_GAP, scale_range


def test_preview_puts_disparity_left_of_uncertainty_with_color_bars_on_their_scales():
    disparity = np.tile(np.linspace(12.0, 53.0, 64, dtype=np.float32), (40, 1))  # a Middlebury range
    uncertainty = np.tile(np.linspace(0.0, 1.0, 64, dtype=np.float32), (40, 1))
    png = encode_preview(disparity, uncertainty, scale_range(disparity))
    preview = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]
    assert preview.shape == (40 + BAR_HEIGHT, 128 + PREVIEW_GAP, 3)
    turbo = cv2.applyColorMap(np.array([[0, 255]], np.uint8), cv2.COLORMAP_TURBO)[0, :, ::-1]
    # the map's own range spans the whole colour map (not the bottom quarter of a fixed 0-192)
    assert np.abs(preview[0, 0].astype(int) - turbo[0]).max() <= 40
    assert np.abs(preview[0, 63].astype(int) - turbo[1]).max() <= 40
    inferno = cv2.applyColorMap(np.array([[255]], np.uint8), cv2.COLORMAP_INFERNO)[0, 0, ::-1]
    assert (preview[0, 127 + PREVIEW_GAP] == inferno).all()
    assert (preview[:, 64 : 64 + PREVIEW_GAP] == 255).all()  # the two bars' end labels stay apart
    assert (preview[40:] == 255).any() and (preview[40:] < 128).any()  # bars: white with dark text


def test_a_fixed_color_scale_is_honoured_and_a_reversed_one_refused():
    disparity = np.full((8, 8), 30.0, np.float32)
    assert scale_range(disparity, 0.0, 192.0) == (0.0, 192.0)
    low, high = scale_range(disparity)
    assert high > low  # a constant map still gets a scale
    with pytest.raises(ValueError, match="above"):
        scale_range(disparity, 50.0, 10.0)
