"""Spec of stereo_data.formats: PFM, 16-bit PNG maps (KITTI), map writers, RGB images, errors."""

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from crestereo_pp.stereo_data.formats import (
    KITTI_SCALE,
    UNCERTAINTY_SCALE,
    FormatError,
    decode_image,
    encode_png16,
    read_image,
    read_kitti_disparity,
    read_pfm,
    write_disparity,
    write_kitti_disparity,
    write_pfm,
    write_uncertainty,
)
from service_helpers import corrupt_jpeg, encode, stereo_pair


def ramp(shape: tuple[int, ...]) -> np.ndarray:
    """Distinct float32 values, so that any flip or transposition shows."""
    return np.arange(np.prod(shape), dtype=np.float32).reshape(shape) * 0.25 - 3.0


@pytest.mark.parametrize("little_endian", [True, False])
@pytest.mark.parametrize("shape", [(5, 7), (5, 7, 3)])
def test_pfm_round_trip_is_exact(tmp_path: Path, shape: tuple[int, ...], little_endian: bool) -> None:
    array = ramp(shape)
    array[1, 2] = np.inf
    write_pfm(tmp_path / "a.pfm", array, little_endian=little_endian)
    back = read_pfm(tmp_path / "a.pfm")
    assert back.dtype == np.float32 and back.shape == shape
    np.testing.assert_array_equal(back, array)


@pytest.mark.parametrize("kind, channels", [(b"Pf", 1), (b"PF", 3)])
@pytest.mark.parametrize("scale, dtype", [(b"-1.0", "<f4"), (b"1.0", ">f4")])
def test_pfm_reader_follows_the_format_rows_bottom_to_top(
    tmp_path: Path, kind: bytes, channels: int, scale: bytes, dtype: str
) -> None:
    stored = ramp((3, 4, channels))  # as on disk: first stored row is the bottom row
    (tmp_path / "a.pfm").write_bytes(kind + b"\n4 3\n" + scale + b"\n" + stored.astype(dtype).tobytes())
    expected = stored[::-1] if channels == 3 else stored[::-1, :, 0]
    np.testing.assert_array_equal(read_pfm(tmp_path / "a.pfm"), expected)


def test_read_pfm_returns_a_writable_native_endian_array(tmp_path: Path) -> None:
    write_pfm(tmp_path / "a.pfm", np.ones((1, 3), np.float32))  # one row: no flip copy
    array = read_pfm(tmp_path / "a.pfm")
    array[0, 0] = 5.0  # a caller may edit what it read
    assert array.dtype == np.dtype("float32") and array.dtype.isnative


def test_pfm_writer_stores_rows_bottom_to_top_little_endian(tmp_path: Path) -> None:
    write_pfm(tmp_path / "a.pfm", np.array([[1, 2], [3, 4]], dtype=np.float32))
    data = (tmp_path / "a.pfm").read_bytes()
    assert data.startswith(b"Pf\n2 2\n-1.0\n")
    np.testing.assert_array_equal(np.frombuffer(data[-16:], "<f4"), [3, 4, 1, 2])


@pytest.mark.parametrize(
    "content", [b"", b"P6\n2 2\n255\n", b"Pf\n4 3\n-1.0\n" + bytes(8), b"Pf\n2 2\n0\n" + bytes(16)]
)
def test_pfm_reader_rejects_bad_files_naming_them(tmp_path: Path, content: bytes) -> None:
    (tmp_path / "bad.pfm").write_bytes(content)
    with pytest.raises(FormatError, match="bad.pfm"):
        read_pfm(tmp_path / "bad.pfm")


def test_format_error_is_a_value_error_and_covers_missing_files(tmp_path: Path) -> None:
    assert issubclass(FormatError, ValueError)
    for reader in (read_pfm, read_kitti_disparity, read_image):
        with pytest.raises(FormatError, match="missing.png"):
            reader(tmp_path / "missing.png")


def test_kitti_disparity_is_value_over_256_with_zero_as_unknown(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "d.png"), np.array([[0, 256, 300], [65535, 1, 0]], dtype=np.uint16))
    disparity = read_kitti_disparity(tmp_path / "d.png")
    assert disparity.dtype == np.float32
    np.testing.assert_array_equal(disparity, [[np.inf, 1.0, 300 / 256], [65535 / 256, 1 / 256, np.inf]])


def test_kitti_writer_round_trips_to_1_over_256_and_encodes_unknown_as_zero(tmp_path: Path) -> None:
    disparity = np.array([[12.3456, np.inf, np.nan], [-2.0, 0.0, 1e-4], [300.0, 255.99, 0.5]])
    write_kitti_disparity(tmp_path / "d.png", disparity)
    encoded = cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED)
    assert encoded.dtype == np.uint16
    np.testing.assert_array_equal(encoded, [[round(12.3456 * 256), 0, 0], [0, 0, 1], [65535, round(255.99 * 256), 128]])
    back = read_kitti_disparity(tmp_path / "d.png")
    assert abs(back[0, 0] - 12.3456) <= 0.5 / 256
    assert np.isinf(back[0, 1:]).all() and np.isinf(back[1, :2]).all()


def decode_png16(data: bytes) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image.dtype == np.uint16 and image.ndim == 2
    return image


def test_the_one_16_bit_png_rule_rounds_half_to_even_keeps_positive_values_and_zeroes_unknown():
    # KITTI's convention for every map: round(value x scale), half to even, clipped to [1, 65535];
    # 0 only where the value is inf, nan or <= 0, so a tiny positive value never reads as unknown.
    disparity = np.array([[1.5, 0.0, np.inf, 1000.0, 1e-4, -3.0, np.nan, 1.5 / 256, 2.5 / 256]], np.float32)
    assert decode_png16(encode_png16(disparity, KITTI_SCALE)).tolist() == [[384, 0, 0, 65535, 1, 0, 0, 2, 2]]
    uncertainty = np.array([[0.0, 1.0, 0.5, 0.25, 1e-6, 2.0, np.nan]], np.float32)
    assert decode_png16(encode_png16(uncertainty, UNCERTAINTY_SCALE)).tolist() == [
        [0, 65535, 32768, 16384, 1, 65535, 0]
    ]
    with pytest.raises(ValueError, match="HxW"):
        encode_png16(np.ones((2, 2, 3)), KITTI_SCALE)


def test_write_kitti_disparity_writes_the_png16_encoding(tmp_path: Path) -> None:
    disparity = np.array([[12.3456, np.inf], [0.0, 300.0]], np.float32)
    write_kitti_disparity(tmp_path / "d.png", disparity)
    assert (tmp_path / "d.png").read_bytes() == encode_png16(disparity, KITTI_SCALE)
    with pytest.raises(FormatError, match="missing"):
        write_kitti_disparity(tmp_path / "missing" / "d.png", disparity)


@pytest.mark.parametrize("suffix", [".pfm", ".png", ".npy"])
def test_map_writers_pick_the_format_by_extension(tmp_path: Path, suffix: str) -> None:
    disparity = np.array([[12.25, np.inf], [0.0, 3.5]], np.float32)
    uncertainty = np.array([[0.0, 0.25], [1.0, 1e-6]], np.float32)
    write_disparity(tmp_path / f"d{suffix}", disparity)
    write_uncertainty(tmp_path / f"u{suffix}", uncertainty)
    if suffix == ".png":  # the one 16-bit rule, x256 for disparity and x65535 for uncertainty
        assert (tmp_path / "d.png").read_bytes() == encode_png16(disparity, KITTI_SCALE)
        assert (tmp_path / "u.png").read_bytes() == encode_png16(uncertainty, UNCERTAINTY_SCALE)
        return
    read = read_pfm if suffix == ".pfm" else np.load
    for name, values in (("d", disparity), ("u", uncertainty)):
        back = read(tmp_path / f"{name}{suffix}")
        assert back.dtype == np.float32
        np.testing.assert_array_equal(back, values)


def test_map_writers_refuse_an_unknown_extension(tmp_path: Path) -> None:
    for writer in (write_disparity, write_uncertainty):
        with pytest.raises(ValueError, match="use .pfm, .png or .npy"):
            writer(tmp_path / "m.tif", np.ones((2, 2), np.float32))
    assert not list(tmp_path.iterdir())


def test_kitti_reader_rejects_8_bit_png(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "d.png"), np.ones((2, 2), dtype=np.uint8))
    with pytest.raises(FormatError, match="16-bit"):
        read_kitti_disparity(tmp_path / "d.png")


def test_read_image_returns_uint8_rgb(tmp_path: Path) -> None:
    bgr = np.zeros((2, 3, 3), dtype=np.uint8)
    bgr[..., 0] = 10  # blue
    bgr[..., 2] = 200  # red
    cv2.imwrite(str(tmp_path / "c.png"), bgr)
    image = read_image(tmp_path / "c.png")
    assert image.dtype == np.uint8 and image.shape == (2, 3, 3)
    assert (image[..., 0] == 200).all() and (image[..., 2] == 10).all()


def test_read_image_replicates_grayscale_unless_asked_to_keep_it(tmp_path: Path) -> None:
    gray = np.array([[0, 50], [100, 255]], dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "g.png"), gray)
    np.testing.assert_array_equal(read_image(tmp_path / "g.png"), np.repeat(gray[..., None], 3, 2))
    np.testing.assert_array_equal(read_image(tmp_path / "g.png", gray_to_rgb=False), gray)


def test_read_image_scales_16_bit_to_8_bit_and_drops_alpha(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "g16.png"), np.array([[0, 257, 65535]], dtype=np.uint16))
    np.testing.assert_array_equal(read_image(tmp_path / "g16.png")[..., 0], [[0, 1, 255]])
    bgra = np.zeros((1, 2, 4), dtype=np.uint8)
    bgra[..., 1], bgra[..., 3] = 77, 9
    cv2.imwrite(str(tmp_path / "a.png"), bgra)
    image = read_image(tmp_path / "a.png")
    assert image.shape == (1, 2, 3) and (image[..., 1] == 77).all()


def test_read_image_rejects_non_images_naming_them(tmp_path: Path) -> None:
    (tmp_path / "text.png").write_text("not an image")
    with pytest.raises(FormatError, match="text.png"):
        read_image(tmp_path / "text.png")
    with pytest.raises(FormatError, match="upload"):
        decode_image(b"\x89PNG broken", source="upload")


def test_a_jpeg_with_corrupt_data_is_refused_rather_than_decoded_into_garbage(tmp_path: Path, capfd) -> None:
    left, _ = stereo_pair()
    broken = corrupt_jpeg(left)
    garbage = cv2.imdecode(np.frombuffer(broken, np.uint8), cv2.IMREAD_COLOR)
    assert garbage is not None  # what OpenCV alone gives: a picture, with a warning on stderr
    path = tmp_path / "left.jpg"
    path.write_bytes(broken)
    capfd.readouterr()
    with pytest.raises(FormatError, match=r"left\.jpg' is a corrupt JPEG \(Corrupt JPEG data: .*\)"):
        read_image(path)
    with pytest.raises(FormatError, match="the image is a corrupt JPEG"):
        decode_image(broken)
    intact = decode_image(encode(left, ".jpg"))
    os.write(2, b"written after the decodes\n")
    printed = capfd.readouterr().err
    assert "Corrupt JPEG" not in printed and "written after the decodes" in printed  # stderr is back
    intact_error = np.abs(intact.astype(int) - left).mean()  # JPEG's loss
    garbage_error = np.abs(cv2.cvtColor(garbage, cv2.COLOR_BGR2RGB).astype(int) - left).mean()
    assert intact_error < 15 and garbage_error > 30
