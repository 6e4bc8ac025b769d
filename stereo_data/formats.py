"""File formats: PFM, 16-bit PNG maps (KITTI disparity and depth, uncertainty), 8-bit RGB images.

Conventions (see docs/CONTRACTS.md): disparity maps are float32 HxW arrays in pixels of the LEFT
image, positive, with ``+inf`` where the ground truth is unknown. Images are uint8 RGB HxWx3.
Every failure to read or write a file raises :class:`FormatError` (a ``ValueError``) naming the file.

16-bit PNG maps follow the KITTI convention for every map (:func:`encode_png16`): the stored value
is ``round(map x scale)`` (half to even) clipped to [1, 65535], and 0 where the map is not finite
or not positive. With ``KITTI_SCALE`` (256) that is KITTI's disparity and depth format; with
``UNCERTAINTY_SCALE`` (65535) an uncertainty in [0, 1] (0 stays 0, a positive one stays >= 1).
Depth also has the convention of RealSense, Kinect and Open3D (``depth_scale=1000``): a 16-bit PNG
in millimetres (:func:`encode_depth_mm_png`), 0 where there is no depth or it is beyond 65.535 m.
"""

from __future__ import annotations

import os
import re
import struct
import sys
import tempfile
import threading
import zlib
from pathlib import Path

import cv2
import numpy as np

__all__ = [
    "FormatError",
    "read_pfm",
    "write_pfm",
    "read_kitti_disparity",
    "write_kitti_disparity",
    "KITTI_SCALE",
    "UNCERTAINTY_SCALE",
    "DEPTH_MM_SCALE",
    "DEPTH_MM_TEXT",
    "encode_png",
    "encode_png16",
    "encode_depth_mm_png",
    "png_with_text",
    "write_disparity",
    "write_uncertainty",
    "write_depth",
    "write_depth_mm",
    "read_image",
    "decode_image",
    "check_pixel_values",
]

PathLike = str | os.PathLike[str]

# PFM header: "PF" (3 channels) or "Pf" (1 channel), width, height, scale; the sign of the scale gives
# the byte order (negative = little-endian). Exactly one whitespace byte separates header and data.
_PFM_HEADER = re.compile(rb"\A(PF|Pf)\s+(\d+)\s+(\d+)\s+([-+0-9.eE]+)\s")
KITTI_SCALE = 256.0  # KITTI 16-bit PNG disparity and depth: value = round(map x 256)
UNCERTAINTY_SCALE = 65535.0  # 16-bit PNG uncertainty in [0, 1]: value = round(map x 65535)
DEPTH_MM_SCALE = 1000.0  # 16-bit PNG depth in millimetres: value = round(metres x 1000), at most 65.535 m
DEPTH_MM_TEXT = "depth_scale=1000; unit=mm; 0=invalid (no depth, or beyond 65.535 m)"
"""What a millimetre depth PNG says of itself, in its tEXt chunk (keyword ``Description``)."""


class FormatError(ValueError):
    """A file is missing, unreadable, or not in the expected format. The message names the file."""


def _read_bytes(path: PathLike) -> bytes:
    try:
        return Path(path).read_bytes()
    except OSError as error:
        raise FormatError(f"cannot read {os.fspath(path)!r}: {error.strerror or error}") from error


def read_pfm(path: PathLike) -> np.ndarray:
    """Read a PFM file (either byte order).

    Returns float32, HxW for ``Pf`` files and HxWx3 for ``PF`` files, rows top-to-bottom (PFM stores
    them bottom-to-top). Values are returned as stored (no scaling by ``abs(scale)``).
    """
    data = _read_bytes(path)
    header = _PFM_HEADER.match(data[:256])
    if header is None:
        raise FormatError(f"{os.fspath(path)!r} is not a PFM file (bad header)")
    channels = 3 if header.group(1) == b"PF" else 1
    width, height = int(header.group(2)), int(header.group(3))
    try:
        scale = float(header.group(4))
    except ValueError:
        raise FormatError(f"{os.fspath(path)!r}: bad PFM scale {header.group(4)!r}") from None
    if scale == 0.0:
        raise FormatError(f"{os.fspath(path)!r}: PFM scale 0 does not define the byte order")
    count = width * height * channels
    payload = data[header.end() :]
    if len(payload) < 4 * count:
        raise FormatError(f"{os.fspath(path)!r}: truncated PFM ({len(payload)} data bytes, {4 * count} expected)")
    dtype = np.dtype("<f4" if scale < 0 else ">f4")
    values = np.frombuffer(payload, dtype=dtype, count=count)
    shape = (height, width, channels) if channels == 3 else (height, width)
    return values.reshape(shape)[::-1].astype(np.float32)  # a native-endian, writable copy


def write_pfm(path: PathLike, array: np.ndarray, *, little_endian: bool = True) -> None:
    """Write a float array as PFM: HxW (or HxWx1) as ``Pf``, HxWx3 as ``PF``.

    ``array`` is top-to-bottom in memory; rows are written bottom-to-top as PFM requires. The scale
    written is -1.0 (little-endian) or 1.0 (big-endian). ``inf`` and ``nan`` are stored as is.
    """
    values = np.asarray(array, dtype=np.float32)
    if values.ndim == 3 and values.shape[2] == 1:
        values = values[:, :, 0]
    if values.ndim == 2:
        kind = b"Pf"
    elif values.ndim == 3 and values.shape[2] == 3:
        kind = b"PF"
    else:
        raise ValueError(f"PFM holds HxW or HxWx3 arrays, got shape {values.shape}")
    height, width = values.shape[:2]
    dtype = np.dtype("<f4" if little_endian else ">f4")
    scale = b"-1.0" if little_endian else b"1.0"
    header = kind + b"\n" + f"{width} {height}".encode() + b"\n" + scale + b"\n"
    Path(path).write_bytes(header + np.ascontiguousarray(values[::-1], dtype=dtype).tobytes())


def read_kitti_disparity(path: PathLike) -> np.ndarray:
    """Read a KITTI 16-bit PNG disparity map: float32 HxW pixels (value / 256), ``+inf`` where 0."""
    encoded = _decode(_read_bytes(path), path, cv2.IMREAD_UNCHANGED)
    if encoded.dtype != np.uint16 or encoded.ndim != 2:
        raise FormatError(
            f"{os.fspath(path)!r}: a KITTI disparity map is a 16-bit single-channel PNG, "
            f"got {encoded.dtype} with shape {encoded.shape}"
        )
    disparity = encoded.astype(np.float32) / KITTI_SCALE
    disparity[encoded == 0] = np.inf
    return disparity


def _write_bytes(path: PathLike, data: bytes) -> None:
    try:
        Path(path).write_bytes(data)
    except OSError as error:
        raise FormatError(f"cannot write {os.fspath(path)!r}: {error.strerror or error}") from error


def encode_png16(values: np.ndarray, scale: float) -> bytes:
    """A float HxW map as a single-channel 16-bit PNG (the file's bytes): value = round(map x
    scale), half to even, in float64, clipped to [1, 65535] so that a tiny positive value stays
    distinguishable from 0 and a huge one saturates; 0 where the map is ``inf``, ``nan`` or <= 0
    (KITTI's "unknown")."""
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 2:
        raise ValueError(f"a 16-bit PNG map is HxW, got shape {values.shape}")
    known = np.isfinite(values) & (values > 0)
    encoded = np.zeros(values.shape, dtype=np.uint16)
    encoded[known] = np.clip(np.rint(values[known] * scale), 1, 65535).astype(np.uint16)
    return encode_png(encoded)


def encode_depth_mm_png(depth: np.ndarray) -> bytes:
    """A float HxW depth map (metres, ``+inf`` where there is none) as a 16-bit PNG in millimetres
    (`encode_png16` at DEPTH_MM_SCALE), which reads back as uint16 mm (``cv2.IMREAD_UNCHANGED``;
    Open3D's default ``depth_scale=1000``). A depth beyond 65.535 m is 0, invalid, rather than a
    saturated 65535; DEPTH_MM_TEXT says so in a tEXt chunk."""
    metres = np.asarray(depth, dtype=np.float64)
    within = np.rint(metres * DEPTH_MM_SCALE) <= 65535
    png = encode_png16(np.where(within, metres, np.inf), DEPTH_MM_SCALE)
    return png_with_text(png, "Description", DEPTH_MM_TEXT)


def png_with_text(png: bytes, keyword: str, text: str) -> bytes:
    """`png` with a tEXt chunk (Latin-1 `keyword` and `text`) after its header chunk (IHDR)."""
    body = b"tEXt" + keyword.encode("latin-1") + b"\0" + text.encode("latin-1")
    chunk = struct.pack(">I", len(body) - 4) + body + struct.pack(">I", zlib.crc32(body))
    header_end = 8 + 8 + 13 + 4  # the signature, then IHDR: length and type, 13 bytes of data, CRC
    return png[:header_end] + chunk + png[header_end:]


def encode_png(image: np.ndarray) -> bytes:
    """The PNG file bytes of a uint8 or uint16 image: HxW, or HxWx3 RGB."""
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)  # OpenCV writes BGR
    ok, png = cv2.imencode(".png", image)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return png.tobytes()


def write_kitti_disparity(path: PathLike, disparity: np.ndarray) -> None:
    """Write a float HxW disparity map (px) as a KITTI 16-bit PNG: value = round(d x 256), 0 for
    ``+inf``, ``nan`` and values <= 0 (unknown), clipped to [1, 65535], so a tiny positive
    disparity stays valid and a huge one saturates at 255.996 px (see :func:`encode_png16`)."""
    _write_bytes(path, encode_png16(disparity, KITTI_SCALE))


def write_disparity(path: PathLike, disparity: np.ndarray) -> None:
    """Write a float HxW disparity map (px) by the path's extension: ``.pfm`` (float32, ``+inf``
    kept), ``.png`` (KITTI 16-bit, x256, 0 = unknown) or ``.npy`` (float32)."""
    _write_map(path, disparity, KITTI_SCALE)


def write_depth(path: PathLike, depth: np.ndarray) -> None:
    """Write a float HxW depth map (metres, ``+inf`` where there is none) by the path's extension:
    ``.pfm`` or ``.npy`` (float32), or ``.png`` (KITTI depth: 16-bit, x256, 0 = none)."""
    _write_map(path, depth, KITTI_SCALE)


def write_depth_mm(path: PathLike, depth: np.ndarray) -> None:
    """Write a float HxW depth map (metres, ``+inf`` where there is none) as a 16-bit PNG in
    millimetres, 0 = none (see :func:`encode_depth_mm_png`)."""
    _write_bytes(path, encode_depth_mm_png(depth))


def write_uncertainty(path: PathLike, uncertainty: np.ndarray) -> None:
    """Write a float HxW uncertainty map in [0, 1] by the path's extension: ``.pfm`` or ``.npy``
    (float32), or ``.png`` (16-bit, x65535, see :func:`encode_png16`)."""
    _write_map(path, uncertainty, UNCERTAINTY_SCALE)


def _write_map(path: PathLike, values: np.ndarray, png_scale: float) -> None:
    suffix = Path(path).suffix.lower()
    if suffix == ".pfm":
        write_pfm(path, values)
    elif suffix == ".png":
        _write_bytes(path, encode_png16(values, png_scale))
    elif suffix == ".npy":
        np.save(path, np.asarray(values, dtype=np.float32))
    else:
        raise ValueError(f"unknown map format {suffix!r} for {os.fspath(path)}: use .pfm, .png or .npy")


def check_pixel_values(image: np.ndarray) -> None:
    """ValueError where an image array of numbers other than uint8 and uint16 cannot be read as
    the 0-255 that every such array is taken as: values that are not finite, outside 0-255, or
    all within [0, 1] (an image scaled to 1, as many libraries keep them: multiply it by 255)."""
    if image.dtype == np.bool_ or not np.issubdtype(image.dtype, np.number):
        raise ValueError(f"expected an image of numbers, got dtype {image.dtype}")
    if image.size == 0:
        return
    low, high = float(np.min(image)), float(np.max(image))
    if not (np.isfinite(low) and np.isfinite(high) and low >= 0 and high <= 255):
        raise ValueError(f"a {image.dtype} image is taken as 0-255, but its values run outside that range")
    if 0 < high <= 1:
        raise ValueError(
            f"a {image.dtype} image is taken as 0-255, but its values all lie within [0, 1]: multiply it by 255"
        )


def read_image(path: PathLike, *, gray_to_rgb: bool = True) -> np.ndarray:
    """Read an image file as uint8 RGB HxWx3 (see :func:`decode_image` for the conversions)."""
    return decode_image(_read_bytes(path), gray_to_rgb=gray_to_rgb, source=path)


def decode_image(data: bytes, *, gray_to_rgb: bool = True, source: PathLike = "<bytes>") -> np.ndarray:
    """Decode an encoded image (PNG, JPEG, ...) to uint8 RGB HxWx3.

    Alpha is dropped; 16-bit images are scaled to 8 bits (value / 257, rounded). A grayscale image
    is replicated to 3 channels, or returned as uint8 HxW when ``gray_to_rgb`` is False.
    ``source`` only names the data in error messages.
    """
    image = _decode(data, source, cv2.IMREAD_UNCHANGED)
    if image.dtype == np.uint16:
        image = ((image.astype(np.uint32) + 128) // 257).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise FormatError(f"{_named(source)}: unsupported pixel type {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        return np.repeat(image[:, :, None], 3, axis=2) if gray_to_rgb else image
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    raise FormatError(f"{_named(source)}: unsupported image shape {image.shape}")


def _decode(data: bytes, source: PathLike, flags: int) -> np.ndarray:
    try:
        image, printed = _imdecode(data, flags) if data else (None, [])
    except cv2.error as error:  # e.g. beyond OPENCV_IO_MAX_IMAGE_PIXELS (OpenCV 5 raises)
        if "Insufficient memory" in str(error):
            raise MemoryError(f"decoding {_named(source)}: {error}") from None
        reason = "larger than the decoder's pixel limit" if "MAX_IMAGE_PIXELS" in str(error) else "corrupt"
        raise FormatError(f"{_named(source)} cannot be decoded ({reason})") from None
    corruption = [line for line in printed if line.startswith(_JPEG_CORRUPTION)]
    if corruption:
        raise FormatError(f"{_named(source)} is a corrupt JPEG ({corruption[0]})")
    if image is None:
        errors = [line for line in printed if "error" in line.lower()]
        reason = errors[-1][:200] if errors else "truncated, corrupt, or a variant OpenCV cannot read"
        raise FormatError(f"{_named(source)} cannot be decoded ({reason})")
    if printed:  # the image decoded: the decoder's warnings are news for whoever reads stderr
        os.write(2, "".join(f"{line}\n" for line in printed).encode())
    return image


_JPEG_CORRUPTION = ("Corrupt JPEG data", "Premature end of JPEG file")
"""libjpeg's warnings that the picture decoded has garbage in it (bad entropy-coded data)."""
_STDERR = threading.Lock()  # one redirection of the process's stderr at a time


def _imdecode(data: bytes, flags: int) -> tuple[np.ndarray | None, list[str]]:
    """``cv2.imdecode``, and the lines its decoder printed meanwhile. The decoders write their
    warnings and errors on stderr (fd 2), which OpenCV does not pass on: libjpeg decodes a JPEG with
    corrupt data to the end, printing a warning, and the picture comes back with shifted or grey
    blocks; libpng says why a PNG cannot be read ("libpng error: IDAT: invalid distance too far
    back"). So fd 2 is read while an image decodes."""
    buffer = np.frombuffer(data, dtype=np.uint8)
    with _STDERR, tempfile.TemporaryFile() as printed:
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(printed.fileno(), 2)
        try:
            image = cv2.imdecode(buffer, flags)
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        printed.seek(0)
        lines = printed.read().decode(errors="replace").splitlines()
    return image, [line.strip() for line in lines if line.strip()]


def _named(source: PathLike) -> str:
    """How messages name the image: its file, or "the image" for bytes without a name."""
    return "the image" if source == "<bytes>" else repr(os.fspath(source))
