"""Uploaded images: dimensions from the file header, then decoding to RGB.

The header is read first so that a small file that would expand to a huge bitmap (a decompression
bomb) is refused before any pixel is decoded.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from crestereo_pp.stereo_data.formats import FormatError, decode_image


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
    if not data:
        raise ImageError("the file is empty", unsupported=False)
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
    """Decode to uint8 HxWx3 RGB with the project's decoder (`stereo_data.formats.decode_image`:
    16-bit scaled to 8, grayscale repeated, alpha dropped, EXIF orientation ignored), checking
    that the pixels have the size the header announced."""
    try:
        image = decode_image(data)
    except FormatError as exc:
        raise ImageError(str(exc), unsupported=False) from None
    if image.shape[:2] != (header.height, header.width):
        raise ImageError(
            f"decoded size {image.shape[1]}x{image.shape[0]} differs from the header's {header.width}x{header.height}",
            unsupported=False,
        )
    return image


def _png_header(data: bytes) -> ImageHeader:
    if data[12:16] != b"IHDR":
        raise ImageError("PNG without an IHDR chunk", unsupported=False)
    width, height = struct.unpack(">II", data[16:24])
    return ImageHeader("PNG", width, height)


# Start-of-frame markers carry the dimensions; C4 (Huffman), C8 (reserved), CC (arithmetic) do not.
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_JPEG_NO_LENGTH = {0x01, *range(0xD0, 0xD9)}


_JPEG_MAX_SEGMENTS = 1024  # before the frame header; real files have a few dozen at most
_JPEG_MAX_FILL = 1024  # fill bytes (0xFF) before the frame header; encoders write none or a few
JPEG_MAX_SCANS = 64
"""Most scans a JPEG may hold. A progressive decoder sweeps the whole image once per scan, so a
small file of thousands of tiny scans costs minutes of CPU; encoders write 1 (baseline) to about
a dozen (progressive)."""


def _jpeg_header(data: bytes) -> ImageHeader:
    """Walk the markers up to the frame header: at most _JPEG_MAX_SEGMENTS segments and
    _JPEG_MAX_FILL fill bytes in all, so the walk is bounded whatever the file holds."""
    offset, fill = 2, 0
    for _ in range(_JPEG_MAX_SEGMENTS):
        if data[offset] != 0xFF:
            raise ImageError("corrupt JPEG marker sequence", unsupported=False)
        while data[offset + 1] == 0xFF:  # fill bytes
            offset += 1
            fill += 1
            if fill > _JPEG_MAX_FILL:
                raise ImageError(
                    f"JPEG with more than {_JPEG_MAX_FILL} fill bytes before its frame header", unsupported=False
                )
        marker = data[offset + 1]
        if marker in _JPEG_NO_LENGTH:
            offset += 2
            continue
        if marker == 0xD9:
            raise ImageError("JPEG without a frame header", unsupported=False)
        (length,) = struct.unpack(">H", data[offset + 2 : offset + 4])
        if marker in _JPEG_SOF:
            precision = data[offset + 4]
            if precision != 8:
                raise ImageError(f"{precision}-bit JPEG; send 8-bit JPEG, or PNG for more bits", unsupported=True)
            scans = data.count(b"\xff\xda")  # SOS: 0xFF 0xDA never occurs inside entropy-coded data
            if scans > JPEG_MAX_SCANS:
                raise ImageError(f"JPEG with {scans} scans; the limit is {JPEG_MAX_SCANS}", unsupported=False)
            height, width = struct.unpack(">HH", data[offset + 5 : offset + 9])
            return ImageHeader("JPEG", width, height)
        offset += 2 + length
    raise ImageError(f"JPEG without a frame header in its first {_JPEG_MAX_SEGMENTS} segments", unsupported=False)


def _bmp_header(data: bytes) -> ImageHeader:
    (dib_size,) = struct.unpack("<I", data[14:18])
    if dib_size == 12:  # OS/2 BITMAPCOREHEADER
        width, height = struct.unpack("<HH", data[18:22])
    else:
        width, height = struct.unpack("<ii", data[18:26])
    return ImageHeader("BMP", abs(width), abs(height))  # negative height = rows stored top-down


_TIFF_WIDTH, _TIFF_HEIGHT, _TIFF_BITS = 256, 257, 258
_TIFF_TILE_WIDTH, _TIFF_TILE_LENGTH, _TIFF_SAMPLE_FORMAT = 322, 323, 339
_TIFF_ORIENTATION = 274
_TIFF_READ = {
    _TIFF_WIDTH,
    _TIFF_HEIGHT,
    _TIFF_BITS,
    _TIFF_TILE_WIDTH,
    _TIFF_TILE_LENGTH,
    _TIFF_SAMPLE_FORMAT,
    _TIFF_ORIENTATION,
}
_TIFF_SHORT, _TIFF_LONG = 3, 4
_TIFF_MAX_VALUES = 16  # values read per tag (BitsPerSample has one per sample)
TIFF_MIN_TILE_LIMIT = 1024
"""A TIFF tile side may exceed the image's own side (rounded up to 16) only up to this many
pixels: the decoder allocates whole tiles, so a small image of one huge tile is a memory bomb."""


def _tiff_header(data: bytes) -> ImageHeader:
    """Size, and the layout facts that decide what decoding costs: unsigned 8- or 16-bit samples
    only (415 otherwise), and tiles no larger than the image needs (TIFF_MIN_TILE_LIMIT); and the
    orientation: pixels as stored only (415 otherwise)."""
    order = "<" if data[:2] == b"II" else ">"
    (ifd,) = struct.unpack(order + "I", data[4:8])
    (count,) = struct.unpack(order + "H", data[ifd : ifd + 2])
    tags: dict[int, list[int]] = {}
    for entry in range(ifd + 2, ifd + 2 + 12 * count, 12):
        tag, kind, values = struct.unpack(order + "HHI", data[entry : entry + 8])
        if tag not in _TIFF_READ:
            continue
        if tag in tags:  # decoders disagree on which one counts: refuse, never guess
            raise ImageError(f"TIFF with a repeated tag {tag}", unsupported=False)
        if kind not in (_TIFF_SHORT, _TIFF_LONG) or not 1 <= values <= _TIFF_MAX_VALUES:
            raise ImageError(f"TIFF tag {tag} of an unexpected type or count", unsupported=False)
        value_format = order + ("H" if kind == _TIFF_SHORT else "I") * values
        inline = struct.calcsize(value_format) <= 4
        (where,) = (entry + 8,) if inline else struct.unpack_from(order + "I", data, entry + 8)
        tags[tag] = list(struct.unpack_from(value_format, data, where))
    if _TIFF_WIDTH not in tags or _TIFF_HEIGHT not in tags:
        raise ImageError("TIFF without width and height tags", unsupported=False)
    width, height = tags[_TIFF_WIDTH][0], tags[_TIFF_HEIGHT][0]
    if any(bits not in (1, 8, 16) for bits in tags.get(_TIFF_BITS, [1])):
        raise ImageError(f"TIFF with {tags[_TIFF_BITS][0]}-bit samples; send 8- or 16-bit", unsupported=True)
    if any(kind != 1 for kind in tags.get(_TIFF_SAMPLE_FORMAT, [1])):
        raise ImageError("TIFF with floating-point or signed samples; send unsigned 8- or 16-bit", unsupported=True)
    orientation = tags.get(_TIFF_ORIENTATION, [1])[0]
    if orientation != 1:  # OpenCV's TIFF decoder turns such pixels round, whatever it is asked
        raise ImageError(
            f"TIFF with orientation {orientation} (its pixels stored turned or mirrored): the service reads "
            "pixels as stored, as a calibration has them; send it with orientation 1, or as PNG",
            unsupported=True,
        )
    for tag, side in ((_TIFF_TILE_WIDTH, width), (_TIFF_TILE_LENGTH, height)):
        tile = tags.get(tag, [0])[0]
        if tile > max(side + 15, TIFF_MIN_TILE_LIMIT):
            raise ImageError(f"TIFF tiles of {tile} px for an image of {side} px", unsupported=False)
    return ImageHeader("TIFF", width, height)
