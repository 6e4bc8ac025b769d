"""The OpenAPI description of `POST /disparity` beyond what FastAPI derives from the route: every
answer with its headers and error examples, and the multipart body."""

from __future__ import annotations

from typing import Any

from crestereo_pp.service.api.schemas import ErrorResponse
from crestereo_pp.service.uploads.multipart import CALIBRATION_FIELD, IMAGE_FIELDS
from crestereo_pp.service.uploads.protocols import MALFORMED, pieces_refusal


def _binary(media_type: str) -> dict[str, Any]:
    return {media_type: {"schema": {"type": "string", "format": "binary"}}}


def _header(description: str, schema_type: str = "string") -> dict[str, Any]:
    return {"description": description, "schema": {"type": schema_type}}


_REQUEST_ID = {"X-Request-Id": _header("The client's `X-Request-Id` if well-formed, else a new id.")}
_RESULT_HEADERS = {
    **_REQUEST_ID,
    "X-Model": _header("Model that computed the result."),
    "X-Weights": _header("First 16 hex digits of the weights' sha256, or `random-init`."),
    "X-Model-Status": _header("`trained`, or `untrained`: the model's maps are not usable (see `GET /models`)."),
    "X-Image-Size": _header("`WIDTHxHEIGHT` of the input images."),
    "X-Batch-Size": _header("Requests computed together with this one.", "integer"),
    "X-Queue-Ms": _header("Time queued before the batch started.", "number"),
    "X-Compute-Ms": _header("Network time of the batch.", "number"),
    "X-Camera": _header(
        "A raw pair's only (sent with a `calibration` part): the rectified left camera that disparity and depth "
        "refer to, as in the JSON answer's `camera`: `focal_px=F; baseline_m=B; cx_px=CX; cy_px=CY`."
    ),
    "X-Row-Offset": _header(
        "With `align_rows` (the default): how far the right image's rows lay off the left's, measured on the pair "
        "before matching, as in the JSON answer's `row_offset`: `centre_px=C; across_px=A; down_px=D; "
        "largest_px=L; tracks=N; aligned=true|false`, or `unmeasured` where the pair has too little texture."
    ),
}
_RETRY_AFTER = {"Retry-After": _header("Seconds to wait before retrying.", "integer")}


def _error_doc(description: str, examples: dict[str, str], headers: dict[str, Any] | None = None) -> dict[str, Any]:
    return {
        "model": ErrorResponse,
        "description": description,
        "headers": {**_REQUEST_ID, **(headers or {})},
        "content": {
            "application/json": {
                "examples": {
                    code: {"summary": message, "value": {"error": {"code": code, "message": message}}}
                    for code, message in examples.items()
                }
            }
        },
    }


RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "The maps, in the requested `format` (`application/json` for json, "
        "`application/x-npz` for npz, `image/png` for the PNG formats, `application/x-ply` for ply). Every "
        "format also carries the answer's facts (model, model_status, weights, image_size, batch_size, "
        "timings, frame, camera, row_offset: the fields of the JSON body but its maps) as one line of JSON "
        "inside its file: npz as the 0-d string array `facts`, PNG as the tEXt chunk `facts`, ply as the "
        "header line `comment facts {...}`.",
        "headers": _RESULT_HEADERS,
        "content": {**_binary("application/x-npz"), **_binary("image/png"), **_binary("application/x-ply")},
    },
    400: _error_doc(
        "The request is not valid HTTP/1.1, or its body came in too many pieces; the connection is closed.",
        {
            "too_many_pieces": pieces_refusal(1029, 1029),
            "malformed_request": MALFORMED,
        },
    ),
    401: _error_doc(
        "`CRESTEREO_API_KEY` is set and the bearer token is missing or wrong.",
        {"unauthorized": "missing or wrong bearer token"},
        {"WWW-Authenticate": _header("`Bearer`.")},
    ),
    408: _error_doc(
        "The request body did not arrive in time; the connection is closed.",
        {"body_timeout": "the request body did not arrive within 60 s"},
    ),
    413: _error_doc(
        "The body or an image is larger than the server's limits.",
        {
            "body_too_large": "request body larger than 33554432 bytes",
            "image_too_large": "left image has 8294400 pixels; the limit for model `lite` is 4194304",
            "decode_too_large": "reading these images needs more than the 768 MiB the server allows per upload; "
            "send smaller or plainer images",
            "calibration_too_large": "a calibration part may have 256 KiB at most",
        },
    ),
    414: _error_doc(
        "The query string is longer than any valid set of options.",
        {"query_too_long": "query string of 384000 bytes; the limit is 4096"},
    ),
    415: _error_doc(
        "Not multipart/form-data, or an upload that is not a supported image.",
        {"unsupported_media_type": "left: not a PNG, JPEG, BMP or TIFF file"},
    ),
    422: _error_doc(
        "Invalid options, fields, images or calibration.",
        {
            "invalid_request": "query.format: Input should be 'json', 'npz', 'png', ...",
            "missing_field": "multipart field `right` is missing",
            "unknown_field": "unknown multipart field `model`; options go in the query string",
            "size_mismatch": "left is 640x480 but right is 640x479",
            "image_too_small": "left is 16x480; width and height must be at least 32",
            "undecodable_image": "right: the image is a corrupt JPEG (Corrupt JPEG data: bad Huffman code)",
            "scale_too_small": "scale 0.05 would run the 256x64 pair at 13x3; each side must stay at least 16 px",
            "request_too_costly": "this pair (2048x2048) with these options would cost 29.5 times a plain request "
            "of the largest image `lite` takes (4194304 pixels); this server allows 4: ask for fewer iterations, "
            "no flip or a smaller scale, or send a smaller pair",
            "decode_too_costly": "reading these images took more than 5 s of CPU; re-encode them plainly "
            "(baseline JPEG, PNG) and try again",
            "model_not_loaded": "model `full` is not loaded by this server (loaded: lite)",
            "invalid_calibration": "calibration `T`: the baseline is zero: the two cameras are at one place",
        },
    ),
    500: _error_doc(
        "The network failed on the batch this request was in.",
        {"inference_failed": "inference failed; logged as error id 3f9a1c2b7d4e"},
    ),
    503: _error_doc(
        "Not ready, shutting down, overloaded, queue full or deadline unmeetable; retry later.",
        {
            "queue_full": "queue full; retry in 2 s",
            "overloaded": "48 requests are in progress, the most this server takes at once",
            "deadline_exceeded": "deadline passed while waiting for the result",
            "loading": "models are still loading",
            "draining": "server is shutting down",
            "unavailable": "models failed to load; see the server log",
        },
        _RETRY_AFTER,
    ),
}

UPLOAD_BODY = {
    "required": True,
    "content": {
        "multipart/form-data": {
            "schema": {
                "type": "object",
                "required": list(IMAGE_FIELDS),
                "additionalProperties": False,
                "properties": {
                    **{
                        name: {
                            "type": "string",
                            "format": "binary",
                            "description": f"{name.capitalize()} image of the pair: PNG, JPEG, BMP or "
                            "TIFF, 8- or 16-bit, grayscale or colour; both images of equal size, at least "
                            "32 px a side and at most 4,194,304 pixels (the server's defaults); the pixels "
                            "as stored (an EXIF orientation tag is not applied).",
                        }
                        for name in IMAGE_FIELDS
                    },
                    CALIBRATION_FIELD: {
                        "type": "array",
                        "minItems": 1,
                        "maxItems": 2,
                        "items": {"type": "string", "format": "binary"},
                        "description": "Only for a raw (unrectified) pair: its camera's calibration, one OpenCV "
                        "file (YAML or JSON as cv2.FileStorage writes it: K1, D1, K2, D2, R, T and image_size, "
                        "or image_width and image_height; T in metres) or two ROS camera_info files "
                        "(left, then right; any YAML style or JSON, as camera_calibration writes them or as "
                        "`ros2 topic echo` prints a CameraInfo), at most 256 KiB each. The service rectifies "
                        "the pair, and depth and metric point clouds need no focal_px or baseline_m; see `frame`.",
                    },
                },
            }
        }
    },
}
