"""Uploaded images: dimensions from the file header, then decoding to RGB.

The header is read first so that a small file that would expand to a huge bitmap (a decompression
bomb) is refused before any pixel is decoded.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import cv2
import numpy as np


class ImageError(ValueError):
    """An upload that is not a usable image; `unsupported` separates "not an image format we read"
    (HTTP 415) from "a known format that is broken" (HTTP 422)."""

    def __init__(self, message: str, *, unsupported: bool) -> None:
        super().__init__(message)
        self.unsupported = unsupported


@dataclass(frozen=True)
class ImageHeader:
    """What the file header says about an image."""

    format: str
    width: int
    height: int

    @property
    def pixels(self) -> int:
        return self.width * self.height


def read_header(data: bytes) -> ImageHeader:
    """Format and dimensions of a PNG, JPEG, BMP or TIFF file, without decoding pixels."""
    try:
        if data.startswith(b"\x89PNG\r\n\x1a\n"):
            return _png_header(data)
        if data.startswith(b"\xff\xd8"):
            return _jpeg_header(data)
        if data.startswith(b"BM"):
            return _bmp_header(data)
        if data[:4] in (b"II*\x00", b"MM\x00*"):
            return _tiff_header(data)
    except (struct.error, IndexError) as exc:
        raise ImageError("truncated image header", unsupported=False) from exc
    raise ImageError("not a PNG, JPEG, BMP or TIFF file", unsupported=True)


def decode_rgb(data: bytes, header: ImageHeader) -> np.ndarray:
    """Decode to float32 HxWx3 RGB in [0, 255]; 16-bit samples are scaled by 255/65535, grayscale
    is repeated over the three channels and alpha is dropped. EXIF orientation is ignored: a
    rectified pair must stay as captured."""
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ImageError(f"cannot decode the {header.format} data", unsupported=False)
    if image.shape[:2] != (header.height, header.width):
        raise ImageError(
            f"decoded size {image.shape[1]}x{image.shape[0]} differs from the header's "
            f"{header.width}x{header.height}", unsupported=False)
    if image.dtype == np.uint8:
        scale = 1.0
    elif image.dtype == np.uint16:
        scale = 255.0 / 65535.0
    else:
        raise ImageError(f"{image.dtype} samples are not supported; send 8- or 16-bit images",
                         unsupported=True)
    if image.ndim == 2:
        rgb = cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    elif image.shape[2] == 3:
        rgb = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    elif image.shape[2] == 4:
        rgb = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    else:
        raise ImageError(f"{image.shape[2]}-channel images are not supported", unsupported=True)
    return rgb.astype(np.float32) * np.float32(scale)


def _png_header(data: bytes) -> ImageHeader:
    if data[12:16] != b"IHDR":
        raise ImageError("PNG without an IHDR chunk", unsupported=False)
    width, height = struct.unpack(">II", data[16:24])
    return ImageHeader("PNG", width, height)


# Start-of-frame markers carry the dimensions; C4 (Huffman), C8 (reserved), CC (arithmetic) do not.
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_JPEG_NO_LENGTH = {0x01, *range(0xD0, 0xD9)}


def _jpeg_header(data: bytes) -> ImageHeader:
    offset = 2
    while True:
        if data[offset] != 0xFF:
            raise ImageError("corrupt JPEG marker sequence", unsupported=False)
        marker = data[offset + 1]
        if marker == 0xFF:  # fill byte
            offset += 1
            continue
        if marker in _JPEG_NO_LENGTH:
            offset += 2
            continue
        if marker == 0xD9:
            raise ImageError("JPEG without a frame header", unsupported=False)
        (length,) = struct.unpack(">H", data[offset + 2:offset + 4])
        if marker in _JPEG_SOF:
            height, width = struct.unpack(">HH", data[offset + 5:offset + 9])
            return ImageHeader("JPEG", width, height)
        offset += 2 + length


def _bmp_header(data: bytes) -> ImageHeader:
    (dib_size,) = struct.unpack("<I", data[14:18])
    if dib_size == 12:  # OS/2 BITMAPCOREHEADER
        width, height = struct.unpack("<HH", data[18:22])
    else:
        width, height = struct.unpack("<ii", data[18:26])
    return ImageHeader("BMP", abs(width), abs(height))  # negative height = rows stored top-down


_TIFF_WIDTH, _TIFF_HEIGHT = 256, 257
_TIFF_SHORT, _TIFF_LONG = 3, 4


def _tiff_header(data: bytes) -> ImageHeader:
    order = "<" if data[:2] == b"II" else ">"
    (ifd,) = struct.unpack(order + "I", data[4:8])
    (count,) = struct.unpack(order + "H", data[ifd:ifd + 2])
    sizes: dict[int, int] = {}
    for entry in range(ifd + 2, ifd + 2 + 12 * count, 12):
        tag, kind = struct.unpack(order + "HH", data[entry:entry + 4])
        if tag in (_TIFF_WIDTH, _TIFF_HEIGHT):
            if kind not in (_TIFF_SHORT, _TIFF_LONG):
                raise ImageError("TIFF size tag of an unexpected type", unsupported=False)
            value_format = order + ("H" if kind == _TIFF_SHORT else "I")
            (sizes[tag],) = struct.unpack_from(value_format, data, entry + 8)
    if _TIFF_WIDTH not in sizes or _TIFF_HEIGHT not in sizes:
        raise ImageError("TIFF without width and height tags", unsupported=False)
    return ImageHeader("TIFF", sizes[_TIFF_WIDTH], sizes[_TIFF_HEIGHT])
