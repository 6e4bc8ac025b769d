"""Spec of the millimetre depth PNG: what RealSense, Kinect and Open3D (depth_scale=1000) read."""

import io
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from crestereo_pp.stereo_data.formats import DEPTH_MM_TEXT, encode_depth_mm_png, write_depth_mm


def test_depth_reads_back_as_uint16_millimetres_with_0_where_there_is_none_or_beyond_65_535_m(tmp_path: Path) -> None:
    depth = np.array([[1.2346, 0.0004, 65.535, 65.536, 400.0, np.inf, np.nan, -1.0, 0.0]], np.float32)
    write_depth_mm(tmp_path / "depth.png", depth)
    read = cv2.imread(str(tmp_path / "depth.png"), cv2.IMREAD_UNCHANGED)
    assert read.dtype == np.uint16 and read.shape == depth.shape
    # a positive depth under half a millimetre stays a depth (1 mm); beyond 65.535 m it is none, not 65535
    assert read.tolist() == [[1235, 1, 65535, 0, 0, 0, 0, 0, 0]]
    metres = read / 1000.0  # Open3D's default depth_scale
    assert metres[0, 2] == 65.535


def test_the_png_says_its_scale_unit_and_invalid_value_in_a_text_chunk() -> None:
    png = encode_depth_mm_png(np.full((4, 6), 2.5, np.float32))
    image = Image.open(io.BytesIO(png))
    image.load()  # reads every chunk: their CRCs are checked
    assert image.text == {"Description": DEPTH_MM_TEXT}
    assert "depth_scale=1000" in DEPTH_MM_TEXT and "unit=mm" in DEPTH_MM_TEXT and "0=invalid" in DEPTH_MM_TEXT
    assert image.mode == "I;16" and np.array(image).tolist() == [[2500] * 6] * 4
