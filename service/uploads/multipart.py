"""The uploads of `POST /disparity`, from the raw body to RGB images: the multipart files `left`
and `right` (`read_pair`), checked from their file headers (`service.uploads.images.read_header`) before
any pixel is decoded, then decoded (`decode_pair`); and the camera's calibration where the pair is
raw (the optional `calibration` part: one OpenCV file, or two ROS camera_info files), parsed and
checked against the images' size.

These functions take untrusted bytes and can be made to work hard: the service runs them in its
decoder processes (`service.uploads.sandbox`), never on the event loop. They raise `UploadError`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
from python_multipart.exceptions import MultipartParseError
from python_multipart.multipart import MultipartParser, parse_options_header

from crestereo_pp.service.uploads.images import ImageError, ImageHeader, decode_rgb, read_header
from crestereo_pp.stereo_data.calibration_files import MAX_CALIBRATION_BYTES
from crestereo_pp.stereo_data.rig import RigError, parse_rig

IMAGE_FIELDS = ("left", "right")
CALIBRATION_FIELD = "calibration"
MAX_PARTS = 16
"""Most parts a form may have before it is refused (it needs two)."""
MAX_BOUNDARY_PADDING = 64
"""Most spaces and tabs a form may have after a boundary line (RFC 2046 allows some; clients send none)."""


class UploadError(Exception):
    """A refused upload: the HTTP status, an error code and a message for the client."""

    def __init__(self, status: int, code: str, message: str) -> None:
        super().__init__(status, code, message)
        self.status, self.code, self.message = status, code, message

    def __str__(self) -> str:
        return self.message


@dataclass(frozen=True)
class ImageLimits:
    """What the images of one request may be: at most `max_pixels` each, at least `min_side`
    pixels wide and high (`model` only names the limit in messages)."""

    model: str
    max_pixels: int
    min_side: int


def boundary_of(content_type: str) -> bytes:
    """The multipart boundary of a `multipart/form-data` Content-Type (UploadError 415 / 422)."""
    kind, options = parse_options_header(content_type)
    if kind != b"multipart/form-data":
        raise UploadError(415, "unsupported_media_type", "send multipart/form-data with files `left` and `right`")
    boundary = options.get(b"boundary", b"")
    if not 1 <= len(boundary) <= 70:  # RFC 2046
        raise UploadError(422, "invalid_multipart", "multipart Content-Type without a valid boundary")
    return boundary


@dataclass(frozen=True)
class Upload:
    """What a form holds: the two image files, the left image's header, and the camera's rig from
    the `calibration` part(s) as `StereoRig.to_json` text (None for a rectified pair)."""

    left: bytes
    right: bytes
    header: ImageHeader
    rig: str | None


def read_pair(body: bytes, content_type: str, limits: ImageLimits) -> Upload:
    """The files `left` and `right` of a multipart body and its optional `calibration` (nothing else
    may be in the form), once both image headers pass `limits` and agree in size, and the
    calibration is usable for images of that size."""
    form = _form(body, boundary_of(content_type))
    left, right = (_one_file(form, name) for name in IMAGE_FIELDS)
    header = check_headers(limits, left, right)
    return Upload(left, right, header, _rig(form.get(CALIBRATION_FIELD, []), header))


def _one_file(form: dict[str, list[tuple[bytes, bool]]], name: str) -> bytes:
    """The content of the field `name`, sent once and as a file (a part with a filename)."""
    given = form.get(name, [])
    if not given:
        raise UploadError(422, "missing_field", f"multipart field `{name}` is missing")
    if len(given) > 1:
        raise UploadError(422, "invalid_field", f"`{name}` was sent {len(given)} times; send one {name} image")
    content, is_file = given[0]
    if not is_file:
        raise UploadError(
            422,
            "invalid_field",
            f"`{name}` was sent as a form value; send the image as a file (curl -F {name}=@{name}.png, not "
            f"-F '{name}=<{name}.png')",
        )
    return content


def _rig(parts: list[tuple[bytes, bool]], header: ImageHeader) -> str | None:
    """The rig of the calibration parts (files or plain values), as JSON; None without any."""
    if not parts:
        return None
    if len(parts) > 2:
        raise _calibration_error("calibration", f"give one OpenCV file or two ROS camera_info files, got {len(parts)}")
    texts = []
    for data, _ in parts:
        if len(data) > MAX_CALIBRATION_BYTES:
            raise UploadError(
                413, "calibration_too_large", f"a calibration part may have {MAX_CALIBRATION_BYTES >> 10} KiB at most"
            )
        try:
            texts.append(data.decode("utf-8"))
        except UnicodeDecodeError:
            raise _calibration_error("calibration", "not UTF-8 text (YAML or JSON)") from None
    try:
        rig = parse_rig(*texts)
    except RigError as error:
        raise _calibration_error(error.field, error.reason) from None
    if rig.image_size != (header.width, header.height):
        width, height = rig.image_size
        raise _calibration_error(
            "image_size", f"the calibration is for {width}x{height} images, the pair is {header.width}x{header.height}"
        )
    return rig.to_json()


def _calibration_error(field: str, reason: str) -> UploadError:
    return UploadError(422, "invalid_calibration", f"calibration `{field}`: {reason}")


def _form(body: bytes, boundary: bytes) -> dict[str, list[tuple[bytes, bool]]]:
    """The parts of a multipart body by field name: (content, whether it is a file) in order."""
    padded = re.search(b"--" + re.escape(boundary) + b"[ \t]{%d}" % (MAX_BOUNDARY_PADDING + 1), body)
    if padded is not None:  # the parser walks such padding byte by byte: seconds per 20 MiB
        raise UploadError(
            422, "invalid_multipart", f"more than {MAX_BOUNDARY_PADDING} bytes of padding after a multipart boundary"
        )
    parts: list[tuple[dict[bytes, bytes], list[bytes]]] = []
    header_name = b""
    closed = False  # the closing boundary was read

    def on_part_begin() -> None:
        if len(parts) == MAX_PARTS:
            raise UploadError(422, "invalid_multipart", f"more than {MAX_PARTS} parts in the form")
        parts.append(({}, []))

    def on_header_field(data: bytes, start: int, end: int) -> None:
        nonlocal header_name
        header_name = data[start:end].lower()

    def on_header_value(data: bytes, start: int, end: int) -> None:
        parts[-1][0][header_name] = parts[-1][0].get(header_name, b"") + data[start:end]

    def on_part_data(data: bytes, start: int, end: int) -> None:
        parts[-1][1].append(data[start:end])

    def on_end() -> None:
        nonlocal closed
        closed = True

    callbacks = {
        "on_part_begin": on_part_begin,
        "on_header_field": on_header_field,
        "on_header_value": on_header_value,
        "on_part_data": on_part_data,
        "on_end": on_end,
    }
    parser = MultipartParser(boundary, callbacks)  # type: ignore[arg-type]
    try:
        parser.write(body)
        parser.finalize()
    except MultipartParseError as exc:
        raise UploadError(422, "invalid_multipart", f"malformed multipart body ({exc})") from None
    if parts and not closed:  # a body cut short: its last part would pass for whole
        raise UploadError(
            422, "invalid_multipart", "the body ends before the closing boundary (`--BOUNDARY--`): it was cut short"
        )
    form: dict[str, list[tuple[bytes, bool]]] = {}
    for headers, chunks in parts:
        _, options = parse_options_header(headers.get(b"content-disposition", b""))
        name = options.get(b"name", b"").decode("utf-8", "replace")
        if name not in (*IMAGE_FIELDS, CALIBRATION_FIELD):
            raise UploadError(
                422,
                "unknown_field",
                f"unknown multipart field `{name[:64]}`; options go in the query string, and the form's fields are "
                "the files `left` and `right`, and `calibration` for a raw pair",
            )
        form.setdefault(name, []).append((b"".join(chunks), b"filename" in options))
    return form


def check_headers(limits: ImageLimits, left: bytes, right: bytes) -> ImageHeader:
    """The left image's header, once both headers pass `limits` and agree."""
    headers = {name: _read_header(name, data) for name, data in zip(IMAGE_FIELDS, (left, right), strict=True)}
    for name, header in headers.items():
        if header.pixels > limits.max_pixels:
            raise UploadError(
                413,
                "image_too_large",
                f"{name} image has {header.pixels} pixels; the limit for model `{limits.model}` is {limits.max_pixels}",
            )
        if min(header.width, header.height) < limits.min_side:
            raise UploadError(
                422,
                "image_too_small",
                f"{name} is {header.width}x{header.height}; width and height must be at least {limits.min_side}",
            )
    left_header, right_header = headers["left"], headers["right"]
    if (left_header.width, left_header.height) != (right_header.width, right_header.height):
        raise UploadError(
            422,
            "size_mismatch",
            f"left is {left_header.width}x{left_header.height} but right is {right_header.width}x{right_header.height}",
        )
    return left_header


def decode_pair(left: bytes, right: bytes) -> tuple[np.ndarray, np.ndarray]:
    """The two uploads as uint8 HxWx3 RGB images (`service.uploads.images.decode_rgb`)."""
    decoded = []
    for name, data in zip(IMAGE_FIELDS, (left, right), strict=True):
        try:
            decoded.append(decode_rgb(data, read_header(data)))
        except ImageError as exc:
            raise _image_error(name, exc) from None
    return decoded[0], decoded[1]


def _read_header(name: str, data: bytes) -> ImageHeader:
    try:
        return read_header(data)
    except ImageError as exc:
        raise _image_error(name, exc) from None


def _image_error(name: str, exc: ImageError) -> UploadError:
    if exc.unsupported:
        return UploadError(415, "unsupported_media_type", f"{name}: {exc}")
    return UploadError(422, "undecodable_image", f"{name}: {exc}")
