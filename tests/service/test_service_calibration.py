"""A raw pair sent with its camera's calibration: rectified by the service, maps and metric depth
in the rectified or the original left frame, and every unusable calibration refused (422, the
field named) before anything is computed."""

from __future__ import annotations

import asyncio
import io
import time
from collections.abc import Awaitable, Callable

import anyio
import cv2
import httpx
import numpy as np
import pytest
from raw_camera import (
    D1,
    D2,
    DEV_BASELINE_M,
    DEV_FOCAL_PX,
    HANG,
    HEIGHT,
    K1,
    K2,
    MALFORMED,
    PLANE_Z,
    WIDTH,
    R,
    T,
    opencv_file,
    opencv_yaml_with,
    raw_view,
    ros_camera_info_files,
    share_within,
    small_dev_sample,
    unrectify,
)

import crestereo_pp.service.uploads.rectifiers
from crestereo_pp.client import ServiceError, StereoClient
from crestereo_pp.service.api.errors import ApiError
from crestereo_pp.service.batching.batcher import DeadlineExceeded
from crestereo_pp.service.uploads.multipart import ImageLimits, UploadError
from crestereo_pp.service.uploads.rectifiers import BYTES_PER_PIXEL, RectifierCache
from crestereo_pp.service.uploads.sandbox import DecoderLimits, DecoderPool
from crestereo_pp.stereo_data.rig import Rectifier, parse_rig
from service_helpers import decode_array, lite_settings, pair_files, serve_asgi, stereo_pair

MIDDLE = (slice(60, -60), slice(100, -60))  # the plane, away from the borders rectification leaves black
NETWORK_ONLY = {"blend_sgbm": "false", "refine_edges": "false"}  # the network's own answer, no host refinement


@pytest.fixture(scope="module")
def raw_pair() -> dict:
    """The multipart files of the raw camera's pair (grey PNGs)."""
    left, right = raw_view(K1, D1, np.eye(3), np.zeros(3)), raw_view(K2, D2, R, T)
    images = [np.clip(image, 0, 255).astype(np.uint8) for image in (left, right)]
    return pair_files(*images)


pytestmark = pytest.mark.anyio


async def test_a_raw_pair_with_its_calibration_gives_metric_depth_in_either_frame(raw_pair, tmp_path):
    calibration = opencv_file(tmp_path / "stereo.yaml").read_bytes()
    files = [*raw_pair.items(), ("calibration", ("stereo.yaml", calibration))]
    async with serve_asgi() as h:
        rectified = await h.client.post("/disparity", files=files)
        original = await h.client.post("/disparity", params={"frame": "original"}, files=files)
    assert rectified.status_code == 200 and original.status_code == 200
    body, body_original = rectified.json(), original.json()
    assert body["frame"] == "rectified" and body_original["frame"] == "original"
    camera = body["camera"]
    assert camera["baseline_m"] == pytest.approx(0.12, abs=1e-3) and 380 < camera["focal_px"] < 440
    # every format names the camera in a header, to the last digit
    for answer in (rectified, original):
        named = dict(item.split("=") for item in answer.headers["X-Camera"].split("; "))
        assert {name: float(value) for name, value in named.items()} == camera
    depth, depth_original = decode_array(body["depth"]), decode_array(body_original["depth"])
    assert depth.shape == depth_original.shape == (HEIGHT, WIDTH)
    assert np.median(depth[MIDDLE]) == pytest.approx(PLANE_Z, rel=0.08)  # metres, from the calibration alone
    assert np.median(depth_original[MIDDLE]) == pytest.approx(PLANE_Z, rel=0.08)
    # The original frame: no counterpart at the corners the rectified image does not reach.
    disparity_original = decode_array(body_original["disparity"])
    uncertainty_original = decode_array(body_original["uncertainty"])
    missing = np.isinf(disparity_original)
    assert 0 < missing.mean() < 0.2
    assert np.isinf(depth_original[missing]).all() and (uncertainty_original[missing] == 1).all()
    # The rectified frame's disparity is the depth's: focal x baseline / depth.
    disparity = decode_array(body["disparity"])
    finite = np.isfinite(depth)
    np.testing.assert_allclose(disparity[finite], camera["focal_px"] * camera["baseline_m"] / depth[finite], rtol=1e-4)


async def test_two_ros_camera_info_parts_are_the_same_camera_as_the_opencv_file(raw_pair, tmp_path):
    left_info, right_info = (path.read_bytes() for path in ros_camera_info_files(tmp_path))
    opencv = opencv_file(tmp_path / "stereo.json").read_bytes()
    async with serve_asgi() as h:
        ros = await h.client.post(
            "/disparity",
            params={"format": "depth_png16"},
            files=[*raw_pair.items(), ("calibration", ("l.yaml", left_info)), ("calibration", ("r.yaml", right_info))],
        )
        cv = await h.client.post(
            "/disparity",
            params={"format": "depth_png16"},
            files=[*raw_pair.items(), ("calibration", ("stereo.json", opencv))],
        )
    assert ros.status_code == cv.status_code == 200
    ros_depth, cv_depth = (cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED) for r in (ros, cv))
    assert ros_depth.dtype == np.uint16
    assert np.median(ros_depth[MIDDLE]) / 256 == pytest.approx(PLANE_Z, rel=0.08)
    assert np.abs(ros_depth.astype(int) - cv_depth.astype(int)).max() <= 1  # the same rectification


BAD_CALIBRATIONS = [
    ({"T": np.zeros(3)}, "T"),  # a baseline of zero
    ({"K1": None}, "K1"),  # missing
    ({"D1": np.zeros(3)}, "D1"),  # a wrong shape
    ({"K2": np.array([[np.nan, 0, 160], [0, 400, 120], [0, 0, 1]])}, "K2"),  # not finite
    ({"R": np.diag([1.0, 1.0, -1.0])}, "R"),  # a reflection: no rotation
    ({"image_width": 640}, "image_size"),  # not the pair's size
    ({"T": np.array([0.0, -0.12, 0.0])}, "T"),  # one camera above the other: cannot be rectified for rows
    ({"T": np.array([-1e300, 0.0, 0.0])}, "T"),  # focal_px x baseline_m beyond what a query may give
    ({"R": cv2.Rodrigues(np.array([0.0, np.pi / 2, 0.0]))[0]}, "R"),  # turned 90 degrees: no pixel would match
    ({"T": np.array([-120.0, 0.0, 0.0])}, "T"),  # in millimetres: depths 1000 times too far, were it answered
    ({"D1": np.array([50.0, -80.0, 0.0, 0.0, 0.0])}, "calibration"),  # rectified into a 9x enlarged sliver
]


@pytest.mark.parametrize(("entries", "field"), BAD_CALIBRATIONS)
async def test_a_bad_calibration_gets_422_naming_the_field_and_nothing_is_computed(raw_pair, tmp_path, entries, field):
    calibration = opencv_file(tmp_path / "bad.yaml", **entries).read_bytes()
    async with serve_asgi() as h:
        response = await h.client.post(
            "/disparity", files=[*raw_pair.items(), ("calibration", ("bad.yaml", calibration))]
        )
        calls = list(h.predictors["lite"].calls)
    assert response.status_code == 422
    error = response.json()["error"]
    assert error["code"] == "invalid_calibration" and f"calibration `{field}`" in error["message"]
    assert calls == []


async def test_calibration_parts_that_are_not_one_calibration_and_options_that_contradict_it_get_clear_errors(
    raw_pair, tmp_path
):
    calibration = opencv_file(tmp_path / "stereo.yaml").read_bytes()
    left, right = stereo_pair()

    def with_parts(*parts: bytes) -> list:
        return [*raw_pair.items(), *(("calibration", (f"c{i}.yaml", part)) for i, part in enumerate(parts))]

    async with serve_asgi() as h:
        answers = {
            "not yaml": await h.client.post("/disparity", files=with_parts(b"\x00\x01 {[ not yaml")),
            "not text": await h.client.post("/disparity", files=with_parts(b"\xff\xfe\xfa")),
            "three parts": await h.client.post("/disparity", files=with_parts(calibration, calibration, calibration)),
            "too large": await h.client.post("/disparity", files=with_parts(b"#" * (300 << 10))),
            "focal given too": await h.client.post(
                "/disparity", params={"focal_px": 400, "baseline_m": 0.1}, files=with_parts(calibration)
            ),
            "original frame of a rectified pair": await h.client.post(
                "/disparity", params={"frame": "original"}, files=pair_files(left, right)
            ),
            "depth without any calibration": await h.client.post(
                "/disparity", params={"format": "depth_png16"}, files=pair_files(left, right)
            ),
        }
        calls = list(h.predictors["lite"].calls)
    expected = {
        "not yaml": (422, "invalid_calibration", "calibration `calibration`: not a YAML or JSON file"),
        "not text": (422, "invalid_calibration", "not UTF-8 text"),
        "three parts": (422, "invalid_calibration", "two ROS camera_info files, got 3"),
        "too large": (413, "calibration_too_large", "256 KiB"),
        "focal given too": (422, "invalid_request", "leave out focal_px"),
        "original frame of a rectified pair": (422, "invalid_request", "frame=original needs a `calibration` part"),
        "depth without any calibration": (422, "invalid_request", "depth_png16 needs a `calibration` part"),
    }
    for name, (status, code, message) in expected.items():
        error = answers[name].json()["error"]
        assert (answers[name].status_code, error["code"]) == (status, code), name
        assert message in error["message"], name
    assert calls == []


async def test_an_empty_calibration_or_ros_files_right_camera_first_are_answered_with_the_fix(raw_pair, tmp_path):
    left_info, right_info = (path.read_bytes() for path in ros_camera_info_files(tmp_path))
    async with serve_asgi() as h:
        swapped = await h.client.post(
            "/disparity",
            files=[*raw_pair.items(), ("calibration", ("r.yaml", right_info)), ("calibration", ("l.yaml", left_info))],
        )
        empty = await h.client.post("/disparity", files=[*raw_pair.items(), ("calibration", ("stereo.yaml", b""))])
        calls = list(h.predictors["lite"].calls)
    assert (swapped.status_code, empty.status_code) == (422, 422)
    assert swapped.json()["error"]["code"] == empty.json()["error"]["code"] == "invalid_calibration"
    message = swapped.json()["error"]["message"]
    assert message.startswith("calibration `calibration`: the files look swapped: the first camera_info is a right")
    assert message.endswith("send the left camera's first, then the right camera's")
    assert empty.json()["error"]["message"] == "calibration `calibration`: the file is empty (no calibration entries)"
    assert calls == []


async def test_a_malformed_calibration_is_answered_422_by_the_decoder_which_is_not_replaced(raw_pair, tmp_path):
    """Each shape of raw_camera.MALFORMED, and the !!binary scalar that held OpenCV's parser for
    10-22 s of CPU, is refused as the calibration it is not: no crash, no timeout, no new process."""
    calibrations = {
        name: opencv_yaml_with(tmp_path / "c.yaml", key, text) for name, (key, text, _) in MALFORMED.items()
    }
    calibrations["binary tag held OpenCV"] = HANG
    fields = {name: field for name, (_, _, field) in MALFORMED.items()} | {"binary tag held OpenCV": "K1"}
    pool = DecoderPool(DecoderLimits(processes=1, memory_bytes=768 << 20, cpu_seconds=5.0))
    await pool.start()

    async def never() -> Exception:
        await asyncio.sleep(3600)
        raise AssertionError("unreachable")

    try:
        for name, calibration in calibrations.items():
            files = [*raw_pair.items(), ("calibration", ("c.yaml", calibration.encode()))]
            request = httpx.Request("POST", "http://service/disparity", files=files)
            with pytest.raises(UploadError) as refused:
                await pool.read_pair(
                    request.read(), request.headers["content-type"], ImageLimits("lite", 4_194_304, 32), never
                )
            assert (refused.value.status, refused.value.code) == (422, "invalid_calibration"), name
            assert refused.value.message.startswith(f"calibration `{fields[name]}`: "), (name, refused.value.message)
        assert pool.restarts == 0
    finally:
        await pool.close()


def test_a_request_under_a_kilobyte_that_held_a_decoder_for_seconds_gets_422_at_once(default_server):
    grey = np.full((32, 32), 128, np.uint8)
    files = [*pair_files(grey, grey).items(), ("calibration", ("c.yaml", HANG.encode()))]
    with httpx.Client(base_url=default_server.base_url, timeout=60) as http:
        request = http.build_request("POST", "/disparity", files=files)
        size = len(request.read())
        started = time.perf_counter()
        response = http.send(request)
        elapsed = time.perf_counter() - started
    assert size < 1000  # bytes
    assert response.status_code == 422 and response.json()["error"]["code"] == "invalid_calibration"
    assert response.json()["error"]["message"].startswith("calibration `K1`: ")
    assert elapsed < 1.0, elapsed  # OpenCV's parser: 10-22 s


def test_the_client_sends_a_calibration_file_over_http(default_server, raw_pair, tmp_path):
    calibration = opencv_file(tmp_path / "stereo.yaml")
    left, right = raw_pair["left"][1], raw_pair["right"][1]
    with StereoClient(default_server.base_url) as service:
        result = service.disparity(left, right, calibration=calibration, frame="original")
        rectified = service.disparity(left, right, calibration=calibration)
        with pytest.raises(ServiceError) as refused:
            service.disparity(left, right, calibration=opencv_file(tmp_path / "bad.yaml", T=np.zeros(3)))
    assert result.depth is not None and result.depth.shape == (HEIGHT, WIDTH)
    assert np.median(result.depth[MIDDLE]) == pytest.approx(PLANE_Z, rel=0.08)
    assert np.isinf(result.disparity).any()  # the original frame's uncovered corners
    # the rectified camera the maps refer to: depth = focal x baseline / disparity
    camera = rectified.camera
    assert camera is not None and camera == result.camera and camera.baseline_m == pytest.approx(0.12, abs=1e-3)
    assert rectified.depth is not None
    finite = np.isfinite(rectified.depth)
    np.testing.assert_allclose(
        rectified.disparity[finite], camera.focal_px * camera.baseline_m / rectified.depth[finite], rtol=1e-4
    )
    assert (refused.value.status, refused.value.code) == (422, "invalid_calibration")
    assert "calibration `T`" in refused.value.message


@pytest.mark.parametrize("change", ["rotation", "distortion"])
async def test_a_real_pair_made_raw_gives_its_true_depth_about_as_well_as_the_rectified_pair(change, tmp_path):
    """The smallest dev pair made raw by a known turn of the right camera, or by lens distortion,
    and sent with the matching calibration: the depth on the raw left image's pixels is within 5 %
    of the truth about as often as the rectified pair's depth is with focal_px and baseline_m
    (the network's own answers: SGBM, which the default blends in, gains less on the resampled
    images of a turned camera: 0.77 of the pixels within 5 % rectified against 0.69 raw)."""
    sample = small_dev_sample()
    raw = unrectify(sample.left, sample.right, sample.disparity, change)
    calibration = opencv_file(tmp_path / "camera.yaml", **raw.calibration).read_bytes()
    async with serve_asgi() as h:
        rectified = await h.client.post(
            "/disparity",
            params={"format": "npz", "focal_px": DEV_FOCAL_PX, "baseline_m": DEV_BASELINE_M, **NETWORK_ONLY},
            files=pair_files(sample.left, sample.right),
        )
        from_raw = await h.client.post(
            "/disparity",
            params={"format": "npz", "frame": "original", **NETWORK_ONLY},
            files=[*pair_files(raw.left, raw.right).items(), ("calibration", ("camera.yaml", calibration))],
        )
    assert rectified.status_code == from_raw.status_code == 200
    with np.errstate(divide="ignore"):
        truth = np.where(sample.valid, DEV_FOCAL_PX * DEV_BASELINE_M / sample.disparity, np.nan)
    baseline = share_within(np.load(io.BytesIO(rectified.content))["depth"], truth)
    share = share_within(np.load(io.BytesIO(from_raw.content))["depth"], raw.depth)
    assert baseline > 0.4  # the comparison means something
    assert share >= baseline - 0.05


# --- rectifiers: built after admission, one at a time, under the deadline, in bounded bytes ------

RIG_BYTES = WIDTH * HEIGHT * BYTES_PER_PIXEL


def rig_json(folder, camera: int) -> str:
    """The rig of camera number `camera`: the raw camera with its baseline a millimetre longer per number."""
    path = opencv_file(folder / f"camera-{camera}.yaml", T=T + np.array([-0.001 * camera, 0.0, 0.0]))
    return parse_rig(path.read_text()).to_json()


@pytest.fixture
def builds(monkeypatch) -> list[str]:
    """The rigs whose rectifiers are built from now on (each build takes at least 0.3 s)."""
    built: list[str] = []
    build = crestereo_pp.service.uploads.rectifiers._build

    def counted(rig: str) -> Rectifier:
        built.append(rig)
        time.sleep(0.3)
        return build(rig)

    monkeypatch.setattr(crestereo_pp.service.uploads.rectifiers, "_build", counted)
    return built


async def never() -> Exception:
    await asyncio.sleep(3600)
    raise AssertionError("unreachable")


def stop_after(seconds: float):
    async def stop() -> Exception:
        await asyncio.sleep(seconds)
        return DeadlineExceeded("the deadline passed", 1)

    return stop


def test_a_rectifier_holds_the_bytes_the_cache_counts_for_it(tmp_path):
    rectifier = Rectifier(parse_rig(opencv_file(tmp_path / "c.yaml").read_text()))
    arrays = [rectifier._back, *(array for maps in rectifier._maps for array in maps)]
    assert sum(array.nbytes for array in arrays) == RIG_BYTES


async def test_rectifiers_are_kept_within_their_bytes_the_least_recently_used_given_up_first(tmp_path, builds):
    rigs = [rig_json(tmp_path, camera) for camera in range(3)]
    cache = RectifierCache(max_bytes=2 * RIG_BYTES)
    for camera in (0, 1, 0, 2, 0, 1):  # camera 1 is the least recently used when camera 2 comes
        async with cache.use(rigs[camera], never) as rectifier:
            assert rectifier is not None and cache.held_bytes <= cache.max_bytes
    assert builds == [rigs[0], rigs[1], rigs[2], rigs[1]]
    assert cache.held_bytes == 2 * RIG_BYTES


async def test_a_rectifier_in_use_is_kept_and_a_request_waiting_for_room_gives_up_at_its_deadline(tmp_path, builds):
    first, second = rig_json(tmp_path, 0), rig_json(tmp_path, 1)
    cache = RectifierCache(max_bytes=RIG_BYTES)
    async with cache.use(first, never):
        started = time.monotonic()
        with pytest.raises(DeadlineExceeded):
            async with cache.use(second, stop_after(0.2)):
                raise AssertionError("no room for a second rectifier")
        assert time.monotonic() - started < 1.0
    async with cache.use(second, never) as rectifier:  # room once the first is let go
        assert rectifier is not None
    assert builds == [first, second]
    assert cache.held_bytes == RIG_BYTES


async def test_requests_that_give_up_waiting_for_their_rectifiers_cost_no_builds(tmp_path, builds):
    """Twelve cameras at once, each request with a deadline shorter than a build: one build runs
    (and is kept for a retry), the others are never started."""
    rigs = [rig_json(tmp_path, camera) for camera in range(12)]
    cache = RectifierCache(max_bytes=256 << 20)

    async def use(rig: str) -> None:
        async with cache.use(rig, stop_after(0.1)):
            raise AssertionError("a build takes longer than the deadline")

    started = time.monotonic()
    answers = await asyncio.gather(*(use(rig) for rig in rigs), return_exceptions=True)
    assert time.monotonic() - started < 0.3  # answered at their deadline, not after the builds
    assert all(isinstance(answer, DeadlineExceeded) for answer in answers), answers
    await asyncio.sleep(0.6)  # the build under way ends
    assert len(builds) == 1 and cache.held_bytes == RIG_BYTES
    async with cache.use(builds[0], never) as rectifier:
        assert rectifier is not None
    assert len(builds) == 1


async def test_a_rig_opencv_cannot_rectify_is_422_and_not_kept(tmp_path):
    cache = RectifierCache(max_bytes=256 << 20)
    with pytest.raises(ApiError) as refused:
        async with cache.use('{"image_size": [320, 240]}', never):
            raise AssertionError("not a rig")
    assert (refused.value.status, refused.value.code) == (422, "invalid_calibration")
    assert cache.held_bytes == 0


async def test_a_raw_request_refused_at_admission_builds_no_rectifier(raw_pair, tmp_path, builds):
    calibration = opencv_file(tmp_path / "stereo.yaml").read_bytes()
    async with serve_asgi(lite_settings(max_queue=1)) as h:
        gated = h.predictors["lite"]
        gated.gate.clear()  # the worker holds the first request; the second waits in the queue

        async def post_and_wait(until: Callable[[], Awaitable[bool]]) -> asyncio.Future[httpx.Response]:
            posting = asyncio.ensure_future(h.client.post("/disparity", files=pair_files(*stereo_pair())))
            with anyio.fail_after(30):
                while not await until():
                    await asyncio.sleep(0.01)
            return posting

        async def computing() -> bool:
            return gated.calls == [1]

        async def queued() -> bool:
            return (await h.client.get("/health")).json()["queue_depth"]["lite"] == 1

        held = [await post_and_wait(computing), await post_and_wait(queued)]
        refused = await h.client.post(
            "/disparity", files=[*raw_pair.items(), ("calibration", ("stereo.yaml", calibration))]
        )
        gated.gate.set()
        answers = await asyncio.gather(*held)
    assert (refused.status_code, refused.json()["error"]["code"]) == (503, "queue_full")
    assert [answer.status_code for answer in answers] == [200, 200]
    assert builds == []
