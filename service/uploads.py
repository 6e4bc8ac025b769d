"""The uploads of `POST /disparity`: the multipart files `left` and `right`, checked from their
file headers (`service.images.read_header`) before any pixel is decoded, then decoded to RGB."""

from __future__ import annotations

import numpy as np
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect, Request

from service.errors import ApiError, bad_input, client_gone
from service.images import ImageError, ImageHeader, decode_rgb, read_header
from service.settings import Settings

IMAGE_FIELDS = ("left", "right")


async def read_uploads(request: Request) -> tuple[bytes, bytes]:
    """The bytes of the multipart files `left` and `right`; nothing else may be in the form."""
    if not request.headers.get("content-type", "").startswith("multipart/form-data"):
        raise bad_input(415, "unsupported_media_type", "send multipart/form-data with files `left` and `right`")
    try:
        form = await request.form(max_files=len(IMAGE_FIELDS) + 2, max_fields=16)
    except StarletteHTTPException as exc:  # malformed multipart body
        raise bad_input(422, "invalid_multipart", str(exc.detail)) from None
    except ClientDisconnect:  # gone mid-upload: nobody reads the answer; logged and counted as 499
        raise client_gone("client disconnected during the upload") from None
    try:
        unknown = sorted(set(form.keys()) - set(IMAGE_FIELDS))
        if unknown:
            raise bad_input(
                422, "unknown_field", f"unknown multipart field `{unknown[0]}`; options go in the query string"
            )
        files = []
        for name in IMAGE_FIELDS:
            values = form.getlist(name)
            if not values:
                raise bad_input(422, "missing_field", f"multipart field `{name}` is missing")
            if len(values) > 1 or not isinstance(values[0], UploadFile):
                raise bad_input(422, "invalid_field", f"`{name}` must be exactly one file")
            files.append(await values[0].read())
        return files[0], files[1]
    finally:
        await form.close()


def check_headers(settings: Settings, model: str, left: bytes, right: bytes) -> ImageHeader:
    """The left image's header, once both headers pass the size limits of `model` and agree."""
    headers = {name: _read_header(name, data) for name, data in zip(IMAGE_FIELDS, (left, right), strict=True)}
    limit = settings.pixel_limit(model)
    for name, header in headers.items():
        if header.pixels > limit:
            raise bad_input(
                413,
                "image_too_large",
                f"{name} image has {header.pixels} pixels; the limit for model `{model}` is {limit}",
            )
        if min(header.width, header.height) < settings.min_image_side:
            raise bad_input(
                422,
                "image_too_small",
                f"{name} is {header.width}x{header.height}; "
                f"width and height must be at least {settings.min_image_side}",
            )
    left_header, right_header = headers["left"], headers["right"]
    if (left_header.width, left_header.height) != (right_header.width, right_header.height):
        raise bad_input(
            422,
            "size_mismatch",
            f"left is {left_header.width}x{left_header.height} but right is {right_header.width}x{right_header.height}",
        )
    return left_header


def decode_pair(left: bytes, right: bytes) -> tuple[np.ndarray, np.ndarray]:
    """The two uploads as uint8 HxWx3 RGB images (`service.images.decode_rgb`)."""
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


def _image_error(name: str, exc: ImageError) -> ApiError:
    if exc.unsupported:
        return bad_input(415, "unsupported_media_type", f"{name}: {exc}")
    return bad_input(422, "undecodable_image", f"{name}: {exc}")
