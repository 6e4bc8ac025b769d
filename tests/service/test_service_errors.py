"""Limits, errors and the API key: status codes and JSON error bodies, before any computing."""

from __future__ import annotations

import struct
import zlib
from collections.abc import AsyncIterator, Callable
from typing import Any

import numpy as np
import pytest

from crestereo_pp.inference.options import parse_iterations, parse_two_pass
from crestereo_pp.service.api.schemas import DisparityOptions
from service_helpers import (
    encode,
    lite_settings,
    metric_total,
    pair_files,
    serve_asgi,
    stereo_pair,
)

pytestmark = pytest.mark.anyio

LEFT, RIGHT = stereo_pair()
PAIR = pair_files(LEFT, RIGHT)


def png_bomb(width: int, height: int) -> bytes:
    """A valid 1-bit greyscale PNG of width x height, all zeros: tiny file, huge bitmap."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    row = b"\x00" * (1 + (width + 7) // 8)
    compressor = zlib.compressobj(9)
    idat = b"".join(compressor.compress(row) for _ in range(height)) + compressor.flush()
    header = struct.pack(">IIBBBBB", width, height, 1, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


BOMB = png_bomb(30_000, 30_000)  # 900 megapixels in about 100 kB
small_left, small_right = stereo_pair(16, 96)
truncated_png = PAIR["left"][1][:200]

# (case, request keyword arguments, status, error code, rejected_total reason)
CASES: list[tuple[str, dict[str, Any], int, str, str]] = [
    (
        "image over the pixel limit is refused from its header: a decompression bomb",
        {"files": {"left": ("l.png", BOMB), "right": ("r.png", BOMB)}},
        413,
        "image_too_large",
        "too_large",
    ),
    (
        "image smaller than the minimum side",
        {"files": pair_files(small_left, small_right)},
        422,
        "image_too_small",
        "bad_input",
    ),
    (
        "left and right of different sizes",
        {"files": {"left": PAIR["left"], "right": ("r.png", encode(RIGHT[:, :-1]))}},
        422,
        "size_mismatch",
        "bad_input",
    ),
    (
        "upload that is not an image",
        {"files": {"left": ("l.txt", b"hello world"), "right": PAIR["right"]}},
        415,
        "unsupported_media_type",
        "bad_input",
    ),
    (
        "image whose data is broken",
        {"files": {"left": ("l.png", truncated_png), "right": PAIR["right"]}},
        422,
        "undecodable_image",
        "bad_input",
    ),
    ("missing right image", {"files": {"left": PAIR["left"]}}, 422, "missing_field", "bad_input"),
    ("option sent as a form field", {"files": PAIR, "data": {"model": "lite"}}, 422, "unknown_field", "bad_input"),
    ("unknown query option", {"files": PAIR, "params": {"colour": "red"}}, 422, "invalid_request", "bad_input"),
    ("unknown format", {"files": PAIR, "params": {"format": "gif"}}, 422, "invalid_request", "bad_input"),
    (
        "focal length without baseline",
        {"files": PAIR, "params": {"focal_px": 700}},
        422,
        "invalid_request",
        "bad_input",
    ),
    (
        "depth PNG without calibration",
        {"files": PAIR, "params": {"format": "depth_png16"}},
        422,
        "invalid_request",
        "bad_input",
    ),
    (
        "model this server did not load",
        {"files": PAIR, "params": {"model": "full"}},
        422,
        "model_not_loaded",
        "bad_input",
    ),
    (
        "deadline header that is not a positive integer",
        {"files": PAIR, "headers": {"X-Request-Timeout-Ms": "soon"}},
        422,
        "invalid_request",
        "bad_input",
    ),
    (
        "query option given twice",
        {"files": PAIR, "params": [("model", "lite"), ("model", "full")]},
        422,
        "invalid_request",
        "bad_input",
    ),
    (
        "calibration whose depth overflows float32",
        {"files": PAIR, "params": {"focal_px": 1e308, "baseline_m": 1e308}},
        422,
        "invalid_request",
        "bad_input",
    ),
    (
        "calibration whose depth underflows float32 (every depth would be 0 m)",
        {"files": PAIR, "params": {"focal_px": 1e-45, "baseline_m": 1e-45}},
        422,
        "invalid_request",
        "bad_input",
    ),
    (
        "preview colour scale beyond any disparity",
        {"files": PAIR, "params": {"format": "png", "color_min": -1e308, "color_max": 1e308}},
        422,
        "invalid_request",
        "bad_input",
    ),
    (
        "empty image file",
        {"files": {"left": ("l.png", b""), "right": PAIR["right"]}},
        422,
        "undecodable_image",
        "bad_input",
    ),
    (
        "body cut short before its closing boundary",
        {
            "content": b'--cut\r\nContent-Disposition: form-data; name="left"; filename="l.png"\r\n\r\n'
            + PAIR["left"][1],
            "headers": {"Content-Type": "multipart/form-data; boundary=cut"},
        },
        422,
        "invalid_multipart",
        "bad_input",
    ),
    (
        "preview colour scale upside down",
        {"files": PAIR, "params": {"format": "png", "color_min": 50, "color_max": 10}},
        422,
        "invalid_request",
        "bad_input",
    ),
    ("body that is not multipart", {"json": {"left": "x", "right": "y"}}, 415, "unsupported_media_type", "bad_input"),
]


@pytest.mark.parametrize(
    ("request_kwargs", "status", "code", "reason"), [case[1:] for case in CASES], ids=[case[0] for case in CASES]
)
async def test_bad_requests_get_a_json_error_and_are_never_computed(request_kwargs, status, code, reason):
    async with serve_asgi() as h:
        response = await h.client.post("/disparity", **request_kwargs)
        metrics = (await h.client.get("/metrics")).text
    assert response.status_code == status, response.text
    assert response.json() == {"error": {"code": code, "message": response.json()["error"]["message"]}}
    assert response.json()["error"]["message"]
    assert response.headers["x-request-id"]
    assert h.predictors["lite"].calls == []
    assert metric_total(metrics, "crestereo_rejected_total", reason=reason) == 1
    assert metric_total(metrics, "crestereo_requests_total", status=str(status)) == 1


async def test_body_over_the_limit_is_refused_from_content_length_and_while_streaming():
    async with serve_asgi(lite_settings(max_body_bytes=5000)) as h:
        declared = await h.client.post("/disparity", files=PAIR)
        multipart = h.client.build_request("POST", "/disparity", files=PAIR)
        body = multipart.read()
        assert len(body) > 5000

        async def chunks() -> AsyncIterator[bytes]:  # no Content-Length: chunked upload
            for start in range(0, len(body), 1000):
                yield body[start : start + 1000]

        streamed = await h.client.post(
            "/disparity", content=chunks(), headers={"Content-Type": multipart.headers["Content-Type"]}
        )
    for response in (declared, streamed):
        assert response.status_code == 413
        assert response.json()["error"]["code"] == "body_too_large"
    assert "content-length" not in streamed.request.headers


async def test_api_key_guards_disparity_and_compares_the_bearer_token():
    async with serve_asgi(lite_settings(api_key="s3cret")) as h:
        missing = await h.client.post("/disparity", files=PAIR)
        wrong = await h.client.post("/disparity", files=PAIR, headers={"Authorization": "Bearer s3cre"})
        # the right key gets past authentication to input validation (no right image: 422)
        right = await h.client.post(
            "/disparity", files={"left": PAIR["left"]}, headers={"Authorization": "Bearer s3cret"}
        )
        open_paths = [
            (await h.client.get(path)).status_code for path in ("/health", "/health/live", "/health/ready", "/metrics")
        ]
    for response in (missing, wrong):
        assert response.status_code == 401
        assert response.json()["error"]["code"] == "unauthorized"
        assert response.headers["www-authenticate"] == "Bearer"
    assert right.status_code == 422
    assert open_paths == [200, 200, 200, 200]


async def test_unknown_paths_and_methods_get_json_errors():
    async with serve_asgi() as h:
        missing = await h.client.get("/nothing")
        wrong_method = await h.client.get("/disparity")
    assert (missing.status_code, missing.json()["error"]["code"]) == (404, "not_found")
    assert (wrong_method.status_code, wrong_method.json()["error"]["code"]) == (405, "method_not_allowed")


def test_bomb_file_is_small_but_would_decode_huge():
    assert len(BOMB) < 500_000
    assert np.frombuffer(BOMB[16:24], ">u4").tolist() == [30_000, 30_000]


async def test_health_probes_answer_head_as_well_as_get():
    async with serve_asgi() as h:
        for path in ("/health", "/health/live", "/health/ready"):
            head, get = await h.client.head(path), await h.client.get(path)
            assert head.status_code == get.status_code == 200, path
            assert head.content == b""


async def test_an_image_over_its_models_own_limit_is_refused_from_its_header():
    async with serve_asgi(lite_settings(model_max_pixels={"lite": 1000})) as h:
        response = await h.client.post("/disparity", files=PAIR)
    assert (response.status_code, response.json()["error"]["code"]) == (413, "image_too_large")
    assert "model `lite` is 1000" in response.json()["error"]["message"]
    assert h.predictors["lite"].calls == []


async def test_a_deadline_the_work_ahead_cannot_meet_is_refused_at_admission():
    async with serve_asgi() as h:
        assert (await h.client.post("/disparity", files=PAIR)).status_code == 200  # measured once
        calls = list(h.predictors["lite"].calls)
        refused = await h.client.post("/disparity", files=PAIR, headers={"X-Request-Timeout-Ms": "1"})
    assert (refused.status_code, refused.json()["error"]["code"]) == (503, "deadline_exceeded")
    assert "cannot be met" in refused.json()["error"]["message"]
    assert int(refused.headers["retry-after"]) >= 1
    assert h.predictors["lite"].calls == calls  # never computed


def message_of(parse: Callable[[str], object], text: str) -> str:
    """The message of the ValueError `parse` raises for `text` (the CLI's own wording)."""
    with pytest.raises(ValueError) as refused:
        parse(text)
    return str(refused.value)


OPTIONS = ", ".join(DisparityOptions.model_fields)

# (query, the whole message of the 422): each names the option and says what it takes
OPTION_MESSAGES: list[tuple[dict[str, str], str]] = [
    ({"iters": "1000000"}, f"query.iters: {message_of(parse_iterations, '1000000')}"),
    ({"iters": "0"}, "query.iters: each iteration count must be 1..99, got '0'"),
    ({"iters": "1,2"}, f"query.iters: {message_of(parse_iterations, '1,2')}"),
    ({"iters": "04"}, "query.iters: iterations are plain counts without leading zeros, such as 4 or 1,2,4, got '04'"),
    ({"two_pass": "maybe"}, f"query.two_pass: {message_of(parse_two_pass, 'maybe')}"),
    ({"bogus": "1"}, f"query.bogus: unknown option; the options are {OPTIONS}"),
    ({"Format": "npz"}, f"query.Format: unknown option; the options are {OPTIONS}"),
    ({"scale": "2"}, "query.scale: must be above 0 and at most 1, got '2'"),
    ({"scale": "0"}, "query.scale: must be above 0 and at most 1, got '0'"),
    ({"scale": "1_0"}, "query.scale: expected a decimal number such as 0.5 or 1e-3, got '1_0'"),
    ({"min_disparity": "-1"}, "query.min_disparity: must be at least 0, got '-1'"),
    ({"max_uncertainty": "2"}, "query.max_uncertainty: must be at least 0 and at most 1, got '2'"),
    ({"color_min": "1e9"}, "query.color_min: must be at least -32766 and at most 32766, got '1e9'"),
    ({"flip": "x"}, "query.flip: must be true or false (or 1 or 0, yes or no, on or off), got 'x'"),
    ({"focal_px": "700"}, "query: give both focal_px and baseline_m, or neither"),
    (
        {"scale": "2", "wat": "1"},
        f"query.scale: must be above 0 and at most 1, got '2'; query.wat: unknown option; the options are {OPTIONS}",
    ),
    ({"max_depth_m": "5"}, "max_depth_m needs a `calibration` part, or focal_px and baseline_m"),
    (
        {"min_disparity": "5"},
        "min_disparity needs a `calibration` part, or focal_px and baseline_m, or format=ply (it bounds depth and "
        "point clouds)",
    ),
]


async def test_a_bad_option_is_answered_with_what_the_option_takes_and_never_computed():
    async with serve_asgi() as h:
        answers = [await h.client.post("/disparity", params=params, files=PAIR) for params, _ in OPTION_MESSAGES]
    for answer, (params, message) in zip(answers, OPTION_MESSAGES, strict=True):
        assert answer.status_code == 422, params
        assert answer.json() == {"error": {"code": "invalid_request", "message": message}}, params
    assert h.predictors["lite"].calls == []


async def test_a_deadline_header_that_is_no_whole_number_or_over_an_hour_is_answered_in_plain_words():
    async with serve_asgi() as h:
        answer = await h.client.post("/disparity", files=PAIR, headers={"X-Request-Timeout-Ms": "soon"})
        too_long = await h.client.post("/disparity", files=PAIR, headers={"X-Request-Timeout-Ms": "3600001"})
    assert answer.json()["error"]["message"] == (
        "header.X-Request-Timeout-Ms: expected a whole number of milliseconds such as 5000, got 'soon'"
    )
    assert (too_long.status_code, too_long.json()["error"]["message"]) == (
        422,
        "header.X-Request-Timeout-Ms: at most 3600000 ms (an hour), got 3600001",
    )


async def test_a_deadline_of_zero_is_under_the_servers_minimum_as_one_is():
    async with serve_asgi() as h:
        answers = [
            await h.client.post("/disparity", files=PAIR, headers={"X-Request-Timeout-Ms": ms}) for ms in ("0", "1")
        ]
    for answer in answers:
        assert (answer.status_code, answer.json()["error"]["code"]) == (503, "deadline_exceeded")
        assert "no request is answered in less than 100 ms here" in answer.json()["error"]["message"]
    assert h.predictors["lite"].calls == []


async def test_depth_limits_apply_where_there_is_depth_or_a_point_cloud():
    async with serve_asgi() as h:
        answers = [
            await h.client.post("/disparity", params=params, files=PAIR)
            for params in (
                {"min_disparity": "5", "focal_px": "400", "baseline_m": "0.1"},
                {"min_disparity": "5", "format": "ply"},  # image-space points: x, y, disparity
                {"max_depth_m": "5", "focal_px": "400", "baseline_m": "0.1"},
                {"max_uncertainty": "1", "format": "ply"},
            )
        ]
    assert [answer.status_code for answer in answers] == [200] * 4


# (multipart files, the whole message of the 422)
FIELD_MESSAGES: list[tuple[list[tuple[str, Any]], str, str]] = [
    (
        [("l", PAIR["left"]), ("r", PAIR["right"])],
        "unknown_field",
        "unknown multipart field `l`; options go in the query string, and the form's fields are the files `left` "
        "and `right`, and `calibration` for a raw pair",
    ),
    (
        [("LEFT", PAIR["left"]), ("right", PAIR["right"])],
        "unknown_field",
        "unknown multipart field `LEFT`; options go in the query string, and the form's fields are the files "
        "`left` and `right`, and `calibration` for a raw pair",
    ),
    (
        [("left", (None, PAIR["left"][1])), ("right", PAIR["right"])],  # curl -F 'left=<L.png': no filename
        "invalid_field",
        "`left` was sent as a form value; send the image as a file (curl -F left=@left.png, not -F 'left=<left.png')",
    ),
    (
        [("left", PAIR["left"]), ("right", PAIR["right"]), ("right", PAIR["right"])],
        "invalid_field",
        "`right` was sent 2 times; send one right image",
    ),
    ([("right", PAIR["right"])], "missing_field", "multipart field `left` is missing"),
]


async def test_image_fields_sent_wrongly_are_answered_with_how_to_send_them():
    async with serve_asgi() as h:
        answers = [await h.client.post("/disparity", files=files) for files, _, _ in FIELD_MESSAGES]
    for answer, (files, code, message) in zip(answers, FIELD_MESSAGES, strict=True):
        assert answer.status_code == 422, files
        assert answer.json() == {"error": {"code": code, "message": message}}, [name for name, _ in files]
    assert h.predictors["lite"].calls == []
