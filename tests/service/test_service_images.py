"""Image files: headers read before decoding, decoding to 8-bit RGB, broken files told apart."""

from __future__ import annotations

import io

import cv2
import numpy as np
import pytest
from PIL import Image

from crestereo_pp.service.uploads.images import ImageError, decode_rgb, read_header
from service_helpers import encode, stereo_pair


@pytest.mark.parametrize("ext", [".png", ".jpg", ".bmp", ".tiff"])
def test_header_gives_format_and_size_of_every_supported_format(ext):
    left, _ = stereo_pair(40, 72)
    header = read_header(encode(left, ext))
    assert (header.width, header.height) == (72, 40)
    assert header.format == {".png": "PNG", ".jpg": "JPEG", ".bmp": "BMP", ".tiff": "TIFF"}[ext]


@pytest.mark.parametrize(
    ("image", "expected"),
    [
        (np.full((40, 72), 200, np.uint8), 200),  # grayscale, 8-bit
        (np.full((40, 72, 3), 65535, np.uint16), 255),  # colour, 16-bit
        (np.dstack([np.full((40, 72, 3), 10, np.uint8), np.zeros((40, 72), np.uint8)]), 10),  # alpha
    ],
)
def test_decoding_gives_8_bit_rgb(image, expected):
    data = cv2.imencode(".png", image)[1].tobytes()
    rgb = decode_rgb(data, read_header(data))
    assert rgb.shape == (40, 72, 3) and rgb.dtype == np.uint8
    assert (rgb == expected).all()


def test_decoding_keeps_rgb_channel_order():
    image = np.zeros((40, 72, 3), np.uint8)
    image[..., 0] = 255  # red
    data = encode(image)
    assert decode_rgb(data, read_header(data))[0, 0].tolist() == [255, 0, 0]


def test_unknown_and_truncated_files_are_told_apart():
    with pytest.raises(ImageError) as unknown:
        read_header(b"GIF89a....")
    with pytest.raises(ImageError) as truncated:
        read_header(b"\x89PNG\r\n\x1a\n\x00\x00")
    assert unknown.value.unsupported and not truncated.value.unsupported


def tiff_with_orientation(image: np.ndarray, orientation: int) -> bytes:
    out = io.BytesIO()
    Image.fromarray(image).save(out, "TIFF", exif={TIFF_ORIENTATION: orientation})
    return out.getvalue()


TIFF_ORIENTATION = 274


@pytest.mark.parametrize("orientation", [2, 3, 6, 8])
def test_a_tiff_whose_orientation_turns_or_mirrors_its_pixels_is_refused_from_its_header(orientation):
    left, _ = stereo_pair(40, 72)
    with pytest.raises(ImageError) as refused:
        read_header(tiff_with_orientation(left, orientation))
    assert refused.value.unsupported and f"orientation {orientation}" in str(refused.value)


def test_a_tiff_oriented_as_stored_is_read_pixel_for_pixel():
    left, _ = stereo_pair(40, 72)
    data = tiff_with_orientation(left, 1)
    assert np.array_equal(decode_rgb(data, read_header(data)), left)
