"""POST /disparity answers, through httpx on the ASGI app with the real lite model."""

from __future__ import annotations

import io
import json
import logging

import cv2
import numpy as np
import pytest
from PIL import Image
from plyfile import PlyData
from raw_camera import small_dev_sample

from crestereo_pp.inference import load_model
from crestereo_pp.service.api.logs import JsonFormatter
from crestereo_pp.service.settings import Settings
from crestereo_pp.stereo_data.visualize import BAR_HEIGHT, PREVIEW_GAP
from service_helpers import (
    HEIGHT,
    WIDTH,
    assert_same_maps,
    cornered_pair,
    decode_array,
    encode,
    lite_settings,
    pair_files,
    serve_asgi,
    stereo_pair,
)
from tests.untrained_weights import UNTRAINED_BAD2, write_untrained

pytestmark = pytest.mark.anyio


async def test_json_answer_has_maps_equal_to_the_predictor_and_says_how_it_was_computed():
    left, right = stereo_pair()
    async with serve_asgi() as h:
        response = await h.client.post("/disparity", files=pair_files(left, right))
        direct = h.predictors["lite"].predict(left, right)
        weights_sha256 = h.predictors["lite"].weights_sha256
    assert response.status_code == 200
    assert response.headers["content-type"] == "application/json"
    body = response.json()
    weights = weights_sha256[:16] if weights_sha256 else "random-init"
    assert body["model"] == "lite" and body["weights"] == weights
    assert body["image_size"] == {"width": WIDTH, "height": HEIGHT}
    assert body["batch_size"] == 1
    assert body["timings"]["queue_ms"] >= 0 and body["timings"]["compute_ms"] > 0
    assert body["depth"] is None
    disparity, uncertainty = decode_array(body["disparity"]), decode_array(body["uncertainty"])
    assert disparity.shape == uncertainty.shape == (HEIGHT, WIDTH)
    np.testing.assert_allclose(disparity, direct.disparity, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(uncertainty, direct.uncertainty, rtol=1e-4, atol=1e-4)
    assert disparity.min() >= 0 and 0 <= uncertainty.min() <= uncertainty.max() <= 1
    assert response.headers["x-model"] == "lite"
    assert response.headers["x-weights"] == weights
    assert response.headers["x-image-size"] == f"{WIDTH}x{HEIGHT}"
    assert response.headers["x-batch-size"] == "1"
    assert "x-camera" not in response.headers  # a rectified pair's camera is the caller's own
    assert float(response.headers["x-compute-ms"]) == pytest.approx(body["timings"]["compute_ms"], abs=0.01)


async def test_every_format_encodes_the_same_maps_and_depth_is_focal_times_baseline_over_disparity():
    left, right = stereo_pair()
    calibration = {"focal_px": 700.0, "baseline_m": 0.5}
    async with serve_asgi() as h:

        async def get(format: str, **params: float) -> bytes:
            response = await h.client.post(
                "/disparity", params={"format": format, **params}, files=pair_files(left, right)
            )
            assert response.status_code == 200, response.text
            assert response.headers["x-image-size"] == f"{WIDTH}x{HEIGHT}"
            return response.content

        body = json.loads(await get("json", **calibration))
        archive = np.load(io.BytesIO(await get("npz", **calibration)))
        preview = cv2.imdecode(np.frombuffer(await get("png"), np.uint8), cv2.IMREAD_UNCHANGED)
        png16 = {
            name: cv2.imdecode(np.frombuffer(await get(f"{name}_png16", **calibration), np.uint8), cv2.IMREAD_UNCHANGED)
            for name in ("disparity", "depth", "uncertainty")
        }
    disparity, uncertainty, depth = (decode_array(body[name]) for name in ("disparity", "uncertainty", "depth"))
    # no depth at or below the default min_disparity of 1 px
    expected_depth = np.where(disparity > 1.0, 700.0 * 0.5 / np.maximum(disparity, 1e-30), np.inf)
    np.testing.assert_allclose(depth, expected_depth, rtol=1e-5)
    assert sorted(archive.files) == ["depth", "disparity", "facts", "uncertainty"]
    np.testing.assert_allclose(archive["disparity"], disparity, atol=1e-4)
    np.testing.assert_allclose(archive["uncertainty"], uncertainty, atol=1e-4)
    assert preview.shape == (HEIGHT + BAR_HEIGHT, 2 * WIDTH + PREVIEW_GAP, 3) and preview.dtype == np.uint8
    for name, values, scale in (
        ("disparity", disparity, 256),
        ("depth", depth, 256),
        ("uncertainty", uncertainty, 65535),
    ):
        image = png16[name]
        assert image.dtype == np.uint16 and image.shape == (HEIGHT, WIDTH)
        valid = np.isfinite(values) & (values > 0) & (values * scale < 65535)
        np.testing.assert_allclose(image[valid] / scale, values[valid], atol=1.0 / scale + 1e-3)
    assert (png16["depth"][~np.isfinite(depth)] == 0).all()


async def test_every_binary_format_carries_the_facts_of_the_json_answer_inside_its_file():
    left, right = cornered_pair()
    answers = {}
    async with serve_asgi() as h:
        for format in ("json", "npz", "png", "disparity_png16", "depth_png16", "uncertainty_png16", "ply"):
            response = await h.client.post(
                "/disparity",
                params={"format": format, "focal_px": 700.0, "baseline_m": 0.5},
                files=pair_files(left, right),
            )
            assert response.status_code == 200, response.text
            answers[format] = response
    maps = ("disparity", "uncertainty", "depth")
    expected = {name: value for name, value in answers.pop("json").json().items() if name not in maps}
    assert expected["row_offset"] is not None and expected["model_status"] == "trained"
    # read back by other readers than the project's: numpy, Pillow (PNG tEXt chunks), plyfile
    ply_comments = PlyData.read(io.BytesIO(answers["ply"].content)).comments
    inside = {
        "npz": str(np.load(io.BytesIO(answers["npz"].content))["facts"]),
        **{name: Image.open(io.BytesIO(answers[name].content)).text["facts"] for name in answers if "png" in name},
        "ply": next(comment.removeprefix("facts ") for comment in ply_comments if comment.startswith("facts ")),
    }
    assert inside.keys() == answers.keys()
    for name, text in inside.items():
        facts = json.loads(text)
        assert "\n" not in text and facts.keys() == expected.keys(), name
        # each request was computed on its own: its own timings, every other fact the same
        assert {**facts, "timings": None} == {**expected, "timings": None}, name
        headers = answers[name].headers
        assert facts["timings"]["compute_ms"] == float(headers["x-compute-ms"]) > 0, name
        assert facts["weights"] == headers["x-weights"] and facts["batch_size"] == int(headers["x-batch-size"]), name


async def test_grayscale_16_bit_and_jpeg_uploads_are_accepted():
    left, right = stereo_pair()
    grey_left, grey_right = (cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) for image in (left, right))
    async with serve_asgi() as h:
        sixteen_bit = await h.client.post(
            "/disparity",
            files={
                "left": ("l.png", encode(left.astype(np.uint16) * 257)),
                "right": ("r.png", encode(right.astype(np.uint16) * 257)),
            },
        )
        eight_bit = await h.client.post("/disparity", files=pair_files(left, right))
        grey = await h.client.post("/disparity", files=pair_files(grey_left, grey_right))
        jpeg = await h.client.post("/disparity", files=pair_files(left, right, ".jpg"))
    assert [r.status_code for r in (sixteen_bit, eight_bit, grey, jpeg)] == [200] * 4
    # 16-bit samples are scaled to the 8-bit range: the same picture gives the same answer
    np.testing.assert_allclose(
        decode_array(sixteen_bit.json()["disparity"]), decode_array(eight_bit.json()["disparity"]), atol=1e-4
    )


@pytest.mark.parametrize(
    ("params", "knobs"),
    [
        ({"two_pass": "true"}, {"two_pass": True}),
        ({"two_pass": "false"}, {"two_pass": False}),
        ({"two_pass": "auto"}, {"two_pass": "auto"}),
        ({"iters": "3"}, {"iters": 3}),
        ({"iters": "1,1,2"}, {"iters": (1, 1, 2)}),
        ({"scale": "0.5"}, {"scale": 0.5}),
        ({"scale": "0.5", "iters": "2", "two_pass": "true"}, {"scale": 0.5, "iters": 2, "two_pass": True}),
        ({"raw_uncertainty": "true"}, {"raw_uncertainty": True}),
        ({"flip": "true"}, {"flip": True}),
        (
            {"flip": "true", "raw_uncertainty": "true", "iters": "2"},
            {"flip": True, "raw_uncertainty": True, "iters": 2},
        ),
    ],
)
async def test_inference_options_are_served_as_the_library_computes_them(params, knobs):
    left, right = stereo_pair()
    async with serve_asgi() as h:
        response = await h.client.post("/disparity", params=params, files=pair_files(left, right))
        direct = h.predictors["lite"].predict(left, right, **knobs)
    assert response.status_code == 200, response.text
    for name in ("disparity", "uncertainty"):
        served = decode_array(response.json()[name])
        assert served.shape == left.shape[:2]
        np.testing.assert_allclose(served, getattr(direct, name), rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize(
    "params",
    [
        {"iters": "0"},
        {"iters": "1,2"},
        {"iters": "4,x,6"},
        {"iters": "100"},
        {"scale": "0"},
        {"scale": "1.5"},
        {"two_pass": "sometimes"},
        {"flip": "upside"},
    ],
)
async def test_bad_iterations_scale_two_pass_or_flip_get_422(params):
    async with serve_asgi() as h:
        response = await h.client.post("/disparity", params=params, files=pair_files(*stereo_pair()))
    assert (response.status_code, response.json()["error"]["code"]) == (422, "invalid_request")


async def test_request_id_is_echoed_when_well_formed_and_replaced_otherwise():
    async with serve_asgi() as h:
        echoed = await h.client.get("/health", headers={"X-Request-Id": "trace-42.a:b"})
        replaced = await h.client.get("/health", headers={"X-Request-Id": "bad id\nforged"})
        generated = await h.client.get("/health")
    assert echoed.headers["x-request-id"] == "trace-42.a:b"
    assert len(replaced.headers["x-request-id"]) == 32 and " " not in replaced.headers["x-request-id"]
    assert generated.headers["x-request-id"] != replaced.headers["x-request-id"]


async def test_logs_are_json_lines_carrying_the_request_id():
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(JsonFormatter())
    async with serve_asgi() as h:
        logging.getLogger("crestereo_pp").addHandler(handler)
        try:
            await h.client.post("/disparity", headers={"X-Request-Id": "req-1"}, files=pair_files(*stereo_pair()))
        finally:
            logging.getLogger("crestereo_pp").removeHandler(handler)
    lines = [json.loads(line) for line in stream.getvalue().splitlines()]
    access = [line for line in lines if line["message"] == "request"]
    assert access == [
        {
            **access[0],
            "request_id": "req-1",
            "method": "POST",
            "path": "/disparity",
            "status": 200,
            "model": "lite",
            "batch_size": 1,
        }
    ]
    assert access[0]["duration_ms"] > 0 and access[0]["level"] == "info"


async def test_models_describe_each_loaded_model_in_open_inference_protocol_shape():
    async with serve_asgi() as h:
        listing = await h.client.get("/models")
        one = await h.client.get("/models/lite")
        missing = await h.client.get("/models/full")
    predictor = h.predictors["lite"]
    assert listing.status_code == one.status_code == 200
    assert listing.json()["models"] == [one.json()]
    info = one.json()
    assert info["name"] == "lite" and info["platform"] == "pytorch"
    assert info["versions"] == [predictor.weights_sha256[:16]]
    assert [t["name"] for t in info["inputs"]] == ["left", "right"]
    assert [(t["name"], t["datatype"], t["shape"]) for t in info["outputs"]] == [
        ("disparity", "FP32", [-1, -1]),
        ("uncertainty", "FP32", [-1, -1]),
    ]
    assert info["parameters"] == predictor.num_parameters and info["iterations"] == [2, 4, 6]
    assert info["max_image_pixels"] == 4_194_304 and info["min_image_side"] == 32
    assert info["max_request_cost"] == 4.0
    assert info["training"]["pairs"] == predictor.training["total_pairs"] > 0
    assert set(info["training"]["dev_metrics"]) == {"epe", "bad1", "bad2", "bad3", "d1_all"}
    assert (missing.status_code, missing.json()["error"]["code"]) == (404, "model_not_found")
    assert info["status"] == "trained"
    assert (info["backend"], info["precision"], info["compiled"]) == ("torch", "fp32", True)


async def test_a_request_may_cost_up_to_the_limit_in_plain_requests_of_the_largest_image_and_no_more():
    # lite's largest image here is the pair's size, and a request may cost two plain ones of it:
    # flip computes everything twice, one more iteration at 1/4 costs 1/12 more, half the scale 0.475
    # (the network's quarter of the pixels; the classical steps stay at the pair's size).
    settings = lite_settings(model_max_pixels={"lite": HEIGHT * WIDTH}, max_request_cost=2.0)
    files = pair_files(*stereo_pair())
    async with serve_asgi(settings) as h:
        at_limit = await h.client.post("/disparity", params={"flip": "true", "two_pass": "false"}, files=files)
        over = await h.client.post("/disparity", params={"flip": "true", "iters": "7"}, files=files)
        scaled = await h.client.post("/disparity", params={"flip": "true", "iters": "7", "scale": "0.5"}, files=files)
        info = (await h.client.get("/models/lite")).json()
    assert at_limit.status_code == 200 and scaled.status_code == 200
    assert over.status_code == 422
    assert over.json()["error"]["code"] == "request_too_costly"
    assert (
        "would cost 2.2 times a plain request of the largest image `lite` takes (6144 pixels)"
        in (over.json()["error"]["message"])
    )
    assert h.predictors["lite"].calls == [1, 1]  # the two within the limit, each a batch of one
    assert info["max_request_cost"] == 2.0


async def test_the_answer_says_how_far_the_right_rows_lay_off_the_left_ones_and_that_they_were_aligned():
    sample = small_dev_sample()  # Tsukuba; its right image moved 1.5 px down, as a drifted rig leaves it
    height, width = sample.left.shape[:2]
    down = cv2.warpAffine(sample.right, np.float32([[1, 0, 0], [0, 1, 1.5]]), (width, height))
    flat = np.full((64, 96, 3), 90, np.uint8)
    fast = {"two_pass": "false", "iters": "1,1,1"}
    async with serve_asgi() as h:
        answer = await h.client.post("/disparity", params=fast, files=pair_files(sample.left, down))
        as_npz = await h.client.post(
            "/disparity", params={**fast, "format": "npz"}, files=pair_files(sample.left, down)
        )
        unaligned = await h.client.post(
            "/disparity", params={**fast, "align_rows": "false"}, files=pair_files(sample.left, down)
        )
        untextured = await h.client.post("/disparity", params={**fast, "format": "npz"}, files=pair_files(flat, flat))
    offset = answer.json()["row_offset"]
    assert offset["centre_px"] == pytest.approx(1.5, abs=0.1) and offset["aligned"] is True
    assert offset["largest_px"] >= abs(offset["centre_px"]) and offset["tracks"] >= 100
    assert set(offset) == {"centre_px", "across_px", "down_px", "largest_px", "tracks", "aligned"}
    named = dict(item.split("=", 1) for item in as_npz.headers["x-row-offset"].split("; "))
    assert {name: json.loads(value) for name, value in named.items()} == offset  # the same in every format
    assert unaligned.json()["row_offset"] is None and "x-row-offset" not in unaligned.headers
    assert untextured.status_code == 200 and untextured.headers["x-row-offset"] == "unmeasured"


async def test_models_platform_names_what_computes_default_requests_now_not_only_pytorch():
    async with serve_asgi() as h:
        gated = h.predictors["lite"]
        on_torch = (await h.client.get("/models/lite")).json()
        gated.backend = "openvino"  # as loaded with CRESTEREO_BACKEND=openvino, its graph still compiling
        gated.ready = lambda iters=None, *, warm_start=False: False
        compiling = (await h.client.get("/models/lite")).json()
        gated.ready = lambda iters=None, *, warm_start=False: True  # the graph is ready
        compiled = (await h.client.get("/models")).json()["models"][0]
    assert (on_torch["backend"], on_torch["compiled"], on_torch["platform"]) == ("torch", True, "pytorch")
    assert (compiling["backend"], compiling["compiled"], compiling["platform"]) == ("openvino", False, "pytorch")
    assert (compiled["backend"], compiled["compiled"], compiled["platform"]) == ("openvino", True, "openvino")


async def test_on_openvino_the_service_says_so_and_answers_with_the_maps_torch_gives(openvino_cache):
    left, right = stereo_pair()
    settings = lite_settings(backend="openvino", precision="fp32", cache_dir=openvino_cache)
    async with serve_asgi(settings) as h:
        info = (await h.client.get("/models/lite")).json()
        predictor = h.predictors["lite"]
        assert predictor.prepare((1, 1, 1))  # exported, or read from the cache another test filled
        runs = predictor.openvino.runs
        answer = await h.client.post("/disparity", params={"iters": "1,1,1"}, files=pair_files(left, right))
    assert (info["backend"], info["precision"]) == ("openvino", "fp32")
    # one pass: a pair under 192 px a side is too small for two_pass=auto's quick pass
    assert answer.status_code == 200 and predictor.openvino.runs == runs + 1
    expected = load_model("lite", backend="torch").predict(left, right, iters=(1, 1, 1))
    assert_same_maps(decode_array(answer.json()["disparity"]), expected.disparity)


async def test_iterations_openvino_has_no_graph_for_cost_what_torch_takes_to_compute_them(openvino_cache):
    # At a limit of one plain request of the pair's size: 1,1,1 costs 0.44 of one, 1,1,2 0.52, but
    # without its graph torch computes it, 2.5 times slower (1.3): refused, saying why.
    limits = {"model_max_pixels": {"lite": HEIGHT * WIDTH}, "max_request_cost": 1.0}
    files = pair_files(*stereo_pair())
    async with serve_asgi(lite_settings(**limits, backend="openvino", cache_dir=openvino_cache)) as h:
        predictor = h.predictors["lite"]
        assert predictor.prepare((1, 1, 1)) and not predictor.ready((1, 1, 2))
        fast = await h.client.post("/disparity", params={"iters": "1,1,1", "two_pass": "false"}, files=files)
        slow = await h.client.post("/disparity", params={"iters": "1,1,2", "two_pass": "false"}, files=files)
    async with serve_asgi(lite_settings(**limits)) as h:  # on torch, 1,1,2 is as fast as it gets
        on_torch = await h.client.post("/disparity", params={"iters": "1,1,2", "two_pass": "false"}, files=files)
    assert fast.status_code == 200 and on_torch.status_code == 200
    assert (slow.status_code, slow.json()["error"]["code"]) == (422, "request_too_costly")
    assert "would cost 1.3 times a plain request" in slow.json()["error"]["message"]
    assert "no fast graph is ready for these iterations, so torch computes them" in slow.json()["error"]["message"]


async def test_an_untrained_model_says_so_in_its_listing_and_on_every_answer(tmp_path):
    left, right = stereo_pair()
    untrained = write_untrained(tmp_path / "full.pt")
    async with serve_asgi(Settings(models=("lite", "full"), weights={"full": untrained})) as h:
        listing = {model["name"]: model for model in (await h.client.get("/models")).json()["models"]}
        full = await h.client.post("/disparity", params={"model": "full"}, files=pair_files(left, right))
        lite = await h.client.post("/disparity", params={"model": "lite"}, files=pair_files(left, right))
    assert listing["full"]["status"] == "untrained" and listing["lite"]["status"] == "trained"
    assert listing["full"]["training"]["dev_metrics"]["bad2"] == UNTRAINED_BAD2  # its record's, shown
    assert full.status_code == 200 and full.headers["X-Model-Status"] == "untrained"
    assert lite.headers["X-Model-Status"] == "trained"
    assert full.json()["model_status"] == "untrained" and lite.json()["model_status"] == "trained"  # in the body too


async def test_a_metric_point_cloud_is_served_as_binary_ply():
    import io

    from plyfile import PlyData

    left, right = stereo_pair()
    params = {"format": "ply", "focal_px": 500.0, "baseline_m": 0.12, "max_uncertainty": 1.0}
    async with serve_asgi() as h:
        response = await h.client.post("/disparity", params=params, files=pair_files(left, right))
        direct = h.predictors["lite"].predict(left, right)
    assert response.status_code == 200 and response.headers["content-type"] == "application/x-ply"
    vertex = PlyData.read(io.BytesIO(response.content))["vertex"]
    kept = direct.disparity > 1.0  # the default min_disparity
    assert len(vertex) == int(kept.sum())
    np.testing.assert_allclose(np.sort(vertex["z"]), np.sort(500.0 * 0.12 / direct.disparity[kept]), rtol=1e-3)


async def test_a_depth_limit_bounds_the_metric_point_cloud_and_needs_a_calibration():
    import io

    from plyfile import PlyData

    left, right = stereo_pair()
    params = {"format": "ply", "focal_px": 500.0, "baseline_m": 0.12}
    async with serve_asgi() as h:
        unbounded = await h.client.post("/disparity", params=params, files=pair_files(left, right))
        everything = PlyData.read(io.BytesIO(unbounded.content))["vertex"]
        limit = float(np.median(everything["z"]))  # about 15 m: a 4 px disparity
        bounded = await h.client.post(
            "/disparity", params={**params, "max_depth_m": limit}, files=pair_files(left, right)
        )
        uncalibrated = await h.client.post(
            "/disparity", params={"format": "ply", "max_depth_m": 3.0}, files=pair_files(left, right)
        )
    ply = PlyData.read(io.BytesIO(bounded.content))
    assert 0 < len(ply["vertex"]) < len(everything) and ply["vertex"]["z"].max() <= limit
    assert "units metres; frame: left camera, x right, y down, z forward" in ply.comments
    assert (
        uncalibrated.status_code == 422
        and "max_depth_m needs a `calibration` part" in uncalibrated.json()["error"]["message"]
    )
