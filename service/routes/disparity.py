"""`POST /disparity`: a rectified stereo pair in, disparity and uncertainty (and depth) out."""

from __future__ import annotations

import time
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Depends, Header, Query, Request, Response
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from service.batching import (
    Batcher,
    ClientDisconnected,
    DeadlineExceeded,
    Draining,
    InferenceFailed,
    JobResult,
    Knobs,
    Predictor,
    QueueFull,
)
from service.dependencies import RuntimeDep, require_api_key
from service.encoding import (
    KITTI_SCALE,
    UNCERTAINTY_SCALE,
    depth_from_disparity,
    encode_array,
    encode_npz,
    encode_png16,
    encode_preview,
)
from service.errors import ApiError
from service.images import ImageError, ImageHeader, decode_rgb, read_header
from service.logs import request_id_var
from service.runtime import ServiceRuntime, weights_identity
from service.schemas import (
    DisparityOptions,
    DisparityResponse,
    ErrorResponse,
    ImageSize,
    OutputFormat,
    Timings,
)
from service.settings import Settings
from stereo_data.pointcloud import Calibration, encode_ply, point_cloud
from stereo_data.visualize import scale_range

router = APIRouter(tags=["disparity"])

IMAGE_FIELDS = ("left", "right")
MAX_TIMEOUT_MS = 3_600_000


def _binary(media_type: str) -> dict[str, Any]:
    return {media_type: {"schema": {"type": "string", "format": "binary"}}}


def _header(description: str, schema_type: str = "string") -> dict[str, Any]:
    return {"description": description, "schema": {"type": schema_type}}


_REQUEST_ID = {"X-Request-Id": _header("The client's `X-Request-Id` if well-formed, else a new id.")}
_RESULT_HEADERS = {
    **_REQUEST_ID,
    "X-Model": _header("Model that computed the result."),
    "X-Weights": _header("First 16 hex digits of the weights' sha256, or `random-init`."),
    "X-Image-Size": _header("`WIDTHxHEIGHT` of the input images."),
    "X-Batch-Size": _header("Requests computed together with this one.", "integer"),
    "X-Queue-Ms": _header("Time queued before the batch started.", "number"),
    "X-Compute-Ms": _header("Network time of the batch.", "number"),
}
_RETRY_AFTER = {"Retry-After": _header("Seconds to wait before retrying.", "integer")}


def _error_doc(description: str, examples: dict[str, str],
               headers: dict[str, Any] | None = None) -> dict[str, Any]:
    return {
        "model": ErrorResponse,
        "description": description,
        "headers": {**_REQUEST_ID, **(headers or {})},
        "content": {"application/json": {"examples": {
            code: {"summary": message, "value": {"error": {"code": code, "message": message}}}
            for code, message in examples.items()}}},
    }


RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "The maps, in the requested `format` (`application/json` for json, "
        "`application/x-npz` for npz, `image/png` for the PNG formats, `application/x-ply` for ply).",
        "headers": _RESULT_HEADERS,
        "content": {**_binary("application/x-npz"), **_binary("image/png"),
                    **_binary("application/x-ply")},
    },
    401: _error_doc("`CRESTEREO_API_KEY` is set and the bearer token is missing or wrong.",
                    {"unauthorized": "missing or wrong bearer token"},
                    {"WWW-Authenticate": _header("`Bearer`.")}),
    413: _error_doc("The body or an image is larger than the server's limits.", {
        "body_too_large": "request body larger than 33554432 bytes",
        "image_too_large": "left image has 8294400 pixels; the limit for model `lite` is 4194304"}),
    415: _error_doc("Not multipart/form-data, or an upload that is not a supported image.", {
        "unsupported_media_type": "left: not a PNG, JPEG, BMP or TIFF file"}),
    422: _error_doc("Invalid options, fields or images.", {
        "invalid_request": "query.format: Input should be 'json', 'npz', 'png', ...",
        "missing_field": "multipart field `right` is missing",
        "unknown_field": "unknown multipart field `model`; options go in the query string",
        "size_mismatch": "left is 640x480 but right is 640x479",
        "image_too_small": "left is 16x480; width and height must be at least 32",
        "undecodable_image": "right: cannot decode the PNG data",
        "model_not_loaded": "model `full` is not loaded by this server (loaded: lite)"}),
    500: _error_doc("The network failed on the batch this request was in.", {
        "inference_failed": "inference failed; logged as error id 3f9a1c2b7d4e"}),
    503: _error_doc("Not ready, shutting down, queue full or deadline unmeetable; retry later.", {
        "queue_full": "queue full; retry in 2 s",
        "deadline_exceeded": "deadline passed while waiting for the result",
        "loading": "models are still loading",
        "draining": "server is shutting down",
        "unavailable": "models failed to load; see the server log"}, _RETRY_AFTER),
}

UPLOAD_BODY = {
    "required": True,
    "content": {"multipart/form-data": {"schema": {
        "type": "object",
        "required": list(IMAGE_FIELDS),
        "additionalProperties": False,
        "properties": {name: {
            "type": "string", "format": "binary",
            "description": f"{name.capitalize()} image of the rectified pair: PNG, JPEG, BMP or "
            "TIFF, 8- or 16-bit, grayscale or colour; both images of equal size."}
            for name in IMAGE_FIELDS},
    }}},
}


@router.post(
    "/disparity",
    summary="Disparity and uncertainty of a rectified stereo pair",
    response_model=DisparityResponse,
    responses=RESPONSES,
    # `{}` beside the bearer scheme: the key is optional (only when CRESTEREO_API_KEY is set).
    openapi_extra={"requestBody": UPLOAD_BODY, "security": [{}]},
    dependencies=[Depends(require_api_key)],
)
async def estimate_disparity(
    request: Request,
    runtime: RuntimeDep,
    options: Annotated[DisparityOptions, Query()],
    timeout_ms: Annotated[int | None, Header(
        alias="X-Request-Timeout-Ms", ge=1, le=MAX_TIMEOUT_MS,
        description="Deadline in milliseconds from arrival: a request that cannot be computed "
        "in time is dropped before computing and answered 503 `deadline_exceeded`.")] = None,
) -> Response:
    """Send the two images as multipart files `left` and `right`; options go in the query string.

    Every answer carries the model, the weights' identity, the image size, the batch size the
    request ran in and its timings (in the JSON body for `format=json`, and as `X-*` headers).
    """
    deadline = None if timeout_ms is None else time.monotonic() + timeout_ms / 1000
    request.state.model = options.model
    _refuse_repeated_options(request)
    batcher = _batcher_for(runtime, options.model)
    left_bytes, right_bytes = await _read_images(request)
    # header checks are pure Python over untrusted bytes: never on the event loop
    header = await run_in_threadpool(
        _check_headers, runtime.settings, options.model, left_bytes, right_bytes)
    try:
        async with batcher.admit(options.model, pixels=header.pixels, deadline=deadline) as admission:
            left, right = await run_in_threadpool(_decode_pair, left_bytes, right_bytes)
            result = await admission.run(
                left, right, knobs=Knobs(options.two_pass, options.iterations, options.scale,
                                          options.raw_uncertainty),
                deadline=deadline,
                is_disconnected=request.is_disconnected, request_id=request_id_var.get())
    except QueueFull as exc:
        raise ApiError(503, "queue_full", str(exc), reject_reason="queue_full",
                       headers={"Retry-After": str(exc.retry_after_s)}) from None
    except Draining as exc:  # SIGTERM came after the check in `_batcher_for`, or drain timed out
        raise _draining(str(exc)) from None
    except DeadlineExceeded as exc:
        raise ApiError(503, "deadline_exceeded", str(exc), reject_reason="deadline",
                       headers={"Retry-After": str(batcher.retry_after(options.model))}) from None
    except ClientDisconnected as exc:  # nobody reads this answer; it shows in logs and metrics
        raise _client_gone(str(exc)) from None
    except InferenceFailed as exc:
        raise ApiError(500, "inference_failed", str(exc)) from None
    request.state.batch_size = result.batch_size
    predictor = runtime.predictors[options.model]
    return await run_in_threadpool(_render, options, predictor, header, result, left)


def _refuse_repeated_options(request: Request) -> None:
    """`?model=lite&model=full` is ambiguous: 422 rather than silently taking one of them."""
    names = [name for name, _ in request.query_params.multi_items()]
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise _bad_input(422, "invalid_request", f"query.{repeated[0]}: given more than once")


def _batcher_for(runtime: ServiceRuntime, model: str) -> Batcher:
    if runtime.state == "failed":
        raise ApiError(503, "unavailable", "models failed to load; see the server log",
                       reject_reason="not_ready", headers={"Retry-After": "60"})
    if runtime.state == "draining":
        raise _draining("server is shutting down")
    if runtime.state == "loading" or runtime.batcher is None:
        raise ApiError(503, "loading", "models are still loading", reject_reason="not_ready",
                       headers={"Retry-After": "5"})
    if model not in runtime.predictors:
        raise ApiError(422, "model_not_loaded", f"model `{model}` is not loaded by this server "
                       f"(loaded: {', '.join(runtime.predictors)})", reject_reason="bad_input")
    return runtime.batcher


def _draining(message: str) -> ApiError:
    return ApiError(503, "draining", message, reject_reason="not_ready",
                    headers={"Retry-After": "1"})


def _client_gone(message: str) -> ApiError:
    return ApiError(499, "client_disconnected", message, reject_reason="disconnect")


def _bad_input(status: int, code: str, message: str) -> ApiError:
    reason = "too_large" if status == 413 else "bad_input"
    return ApiError(status, code, message, reject_reason=reason)


async def _read_images(request: Request) -> tuple[bytes, bytes]:
    """The bytes of the multipart files `left` and `right`; nothing else may be in the form."""
    if not request.headers.get("content-type", "").startswith("multipart/form-data"):
        raise _bad_input(415, "unsupported_media_type",
                         "send multipart/form-data with files `left` and `right`")
    try:
        form = await request.form(max_files=len(IMAGE_FIELDS) + 2, max_fields=16)
    except StarletteHTTPException as exc:  # malformed multipart body
        raise _bad_input(422, "invalid_multipart", str(exc.detail)) from None
    except ClientDisconnect:  # gone mid-upload: nobody reads the answer; logged and counted as 499
        raise _client_gone("client disconnected during the upload") from None
    try:
        unknown = sorted(set(form.keys()) - set(IMAGE_FIELDS))
        if unknown:
            raise _bad_input(422, "unknown_field", f"unknown multipart field `{unknown[0]}`; "
                             "options go in the query string")
        files = []
        for name in IMAGE_FIELDS:
            values = form.getlist(name)
            if not values:
                raise _bad_input(422, "missing_field", f"multipart field `{name}` is missing")
            if len(values) > 1 or not isinstance(values[0], UploadFile):
                raise _bad_input(422, "invalid_field", f"`{name}` must be exactly one file")
            files.append(await values[0].read())
        return files[0], files[1]
    finally:
        await form.close()


def _check_headers(settings: Settings, model: str, left: bytes, right: bytes) -> ImageHeader:
    """Dimension checks from the file headers, before any pixel is decoded."""
    headers = {name: _read_header(name, data) for name, data in zip(IMAGE_FIELDS, (left, right), strict=True)}
    limit = settings.pixel_limit(model)
    for name, header in headers.items():
        if header.pixels > limit:
            raise _bad_input(413, "image_too_large", f"{name} image has {header.pixels} pixels; "
                             f"the limit for model `{model}` is {limit}")
        if min(header.width, header.height) < settings.min_image_side:
            raise _bad_input(422, "image_too_small", f"{name} is {header.width}x{header.height}; "
                             f"width and height must be at least {settings.min_image_side}")
    left_header, right_header = headers["left"], headers["right"]
    if (left_header.width, left_header.height) != (right_header.width, right_header.height):
        raise _bad_input(422, "size_mismatch", f"left is {left_header.width}x{left_header.height} "
                         f"but right is {right_header.width}x{right_header.height}")
    return left_header


def _read_header(name: str, data: bytes) -> ImageHeader:
    try:
        return read_header(data)
    except ImageError as exc:
        raise _image_error(name, exc) from None


def _decode_pair(left: bytes, right: bytes) -> tuple[np.ndarray, np.ndarray]:
    decoded = []
    for name, data in zip(IMAGE_FIELDS, (left, right), strict=True):
        try:
            decoded.append(decode_rgb(data, read_header(data)))
        except ImageError as exc:
            raise _image_error(name, exc) from None
    return decoded[0], decoded[1]


def _image_error(name: str, exc: ImageError) -> ApiError:
    if exc.unsupported:
        return _bad_input(415, "unsupported_media_type", f"{name}: {exc}")
    return _bad_input(422, "undecodable_image", f"{name}: {exc}")


def _render(options: DisparityOptions, predictor: Predictor, header: ImageHeader,
            result: JobResult, left: np.ndarray) -> Response:
    """The answer in the requested format, with the result facts as headers."""
    weights = weights_identity(predictor)
    queue_ms, compute_ms = result.queue_seconds * 1000, result.compute_seconds * 1000
    headers = {
        "X-Model": predictor.name, "X-Weights": weights,
        "X-Image-Size": f"{header.width}x{header.height}",
        "X-Batch-Size": str(result.batch_size),
        "X-Queue-Ms": f"{queue_ms:.2f}", "X-Compute-Ms": f"{compute_ms:.2f}",
    }
    depth = None
    if options.focal_px is not None and options.baseline_m is not None:
        depth = depth_from_disparity(result.disparity, options.focal_px, options.baseline_m)
    match options.format:
        case OutputFormat.json:
            body = DisparityResponse(
                model=options.model, weights=weights,
                image_size=ImageSize(width=header.width, height=header.height),
                batch_size=result.batch_size,
                timings=Timings(queue_ms=round(queue_ms, 2), compute_ms=round(compute_ms, 2)),
                disparity=encode_array(result.disparity),
                uncertainty=encode_array(result.uncertainty),
                depth=None if depth is None else encode_array(depth))
            return Response(body.model_dump_json(), media_type="application/json", headers=headers)
        case OutputFormat.npz:
            maps = {"disparity": result.disparity, "uncertainty": result.uncertainty}
            if depth is not None:
                maps["depth"] = depth
            return Response(encode_npz(maps), media_type="application/x-npz", headers=headers)
        case OutputFormat.png:
            content = encode_preview(result.disparity, result.uncertainty, scale_range(
                result.disparity, options.color_min, options.color_max))
        case OutputFormat.disparity_png16:
            content = encode_png16(result.disparity, KITTI_SCALE)
        case OutputFormat.depth_png16:
            assert depth is not None  # DisparityOptions requires the calibration for it
            content = encode_png16(depth, KITTI_SCALE)
        case OutputFormat.uncertainty_png16:
            content = encode_png16(result.uncertainty, UNCERTAINTY_SCALE)
        case OutputFormat.ply:
            calibration = None if options.focal_px is None or options.baseline_m is None else Calibration(
                options.focal_px, options.baseline_m, options.cx_px, options.cy_px)
            points, colours = point_cloud(result.disparity, left, result.uncertainty, calibration,
                                          options.max_uncertainty)
            return Response(encode_ply(points, colours), media_type="application/x-ply", headers=headers)
    return Response(content, media_type="image/png", headers=headers)
