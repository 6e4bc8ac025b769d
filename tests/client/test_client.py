"""`client.StereoClient` / `AsyncStereoClient` against a real uvicorn process on loopback."""

from __future__ import annotations

import asyncio
import io
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import cv2
import numpy as np
import pytest
from plyfile import PlyData
from raw_camera import small_dev_sample

from crestereo_pp.client import AsyncStereoClient, DisparityResult, Options, RowOffset, ServiceError, StereoClient
from crestereo_pp.client.stereo_client import _encode
from crestereo_pp.inference import NETWORK_ONLY
from panned_frames import panned_frames
from service_helpers import encode, quiet_load_model, run_uvicorn, stereo_pair


def test_the_sync_client_returns_the_library_maps_as_arrays(default_server):
    left, right = stereo_pair()
    with StereoClient(default_server.base_url) as service:
        result = service.disparity(left, right, iters=(1, 2, 3), focal_px=700.0, baseline_m=0.1)
        models = service.models()
        health = service.health()
    direct = quiet_load_model("lite").predict(left, right, iters=(1, 2, 3))
    assert result.disparity.dtype == np.float32 and result.disparity.shape == left.shape[:2]
    np.testing.assert_allclose(result.disparity, direct.disparity, rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(result.uncertainty, direct.uncertainty, rtol=1e-4, atol=1e-4)
    assert result.depth is not None and result.depth.shape == left.shape[:2]
    assert result.model == "lite" and result.trained and result.batch_size >= 1 and result.compute_ms > 0
    assert result.camera is None  # a rectified pair: its camera is the caller's
    assert [m["name"] for m in models] == ["lite"] and health["status"] == "ready"


def test_the_network_answer_without_the_host_refinements_is_asked_for_by_options(default_server):
    left, right = stereo_pair()
    with StereoClient(default_server.base_url) as service:
        default = service.disparity(left, right)
        blended = service.disparity(left, right, refine_edges=False)
        own = service.disparity(left, right, **NETWORK_ONLY)
    direct = quiet_load_model("lite").predict(left, right, **NETWORK_ONLY)
    np.testing.assert_allclose(own.disparity, direct.disparity, rtol=1e-4, atol=1e-3)
    assert 0.1 < np.abs(blended.disparity - own.disparity).max() <= 2.0 + 1e-3  # blend_sgbm reached the service
    assert np.abs(default.disparity - blended.disparity).max() > 0.1  # and refine_edges


def test_files_and_bytes_are_sent_as_they_are(default_server, tmp_path):
    left, right = stereo_pair()
    (tmp_path / "l.png").write_bytes(encode(left))
    with StereoClient(default_server.base_url) as service:
        from_files = service.disparity(tmp_path / "l.png", encode(right))
        from_arrays = service.disparity(left, right)
    np.testing.assert_array_equal(from_files.disparity, from_arrays.disparity)


def test_arrays_are_sent_as_the_library_takes_them_and_out_of_range_values_refused(default_server):
    left, right = stereo_pair()
    between_levels = left.astype(np.float32) * 0.7 + 0.45  # what an 8-bit PNG cannot hold
    sent = cv2.imdecode(np.frombuffer(_encode(between_levels), np.uint8), cv2.IMREAD_UNCHANGED)
    assert sent.dtype == np.uint16  # read by the service as 0-255 again, within 1/514 of a level
    np.testing.assert_allclose(sent[:, :, ::-1] * (255 / 65535), between_levels, atol=1 / 514 + 1e-6)
    alpha = np.full(left.shape[:2], 7, np.uint8)
    with StereoClient(default_server.base_url) as service:
        plain = service.disparity(left, right)
        with_alpha = service.disparity(np.dstack([left, alpha]), right)  # the alpha dropped
        as_numbers = service.disparity(between_levels, right.astype(np.int64))  # taken as 0-255
        with pytest.raises(ValueError, match="taken as 0-255, but its values run outside that range"):
            service.disparity(left / 255.0 * 300.0, right)
        with pytest.raises(ValueError, match=r"values all lie within \[0, 1\]: multiply it by 255"):
            service.disparity(left / 255.0, right / 255.0)  # an image scaled to 1, as many libraries keep them
        with pytest.raises(ValueError, match="HxWx4"):
            service.disparity(left[:, :, :2], right)
    np.testing.assert_array_equal(with_alpha.disparity, plain.disparity)
    assert as_numbers.disparity.shape == left.shape[:2]


def test_error_answers_raise_typed_errors_with_the_services_code(default_server):
    left, right = stereo_pair()
    with StereoClient(default_server.base_url) as service:
        with pytest.raises(ServiceError) as not_an_image:
            service.disparity(b"hello world", right)
        with pytest.raises(ServiceError) as bad_option:
            service.disparity(left, right, scale=2.0)
    assert (not_an_image.value.status, not_an_image.value.code) == (415, "unsupported_media_type")
    assert (bad_option.value.status, bad_option.value.code) == (422, "invalid_request")


def test_a_point_cloud_comes_back_as_points_colours_and_the_ply_file(default_server):
    right, left = stereo_pair()  # each left pixel 4 px right of its match: disparities about 4
    rig = {"focal_px": 500.0, "baseline_m": 0.12}
    with StereoClient(default_server.base_url) as service:
        maps = service.disparity(left, right, **rig)
        cloud = service.point_cloud(left, right, cx_px=0.0, cy_px=0.0, **rig)
        image_space = service.point_cloud(left, right, max_uncertainty=0.001)
    kept = maps.disparity > 1.0  # the service's default min_disparity
    assert cloud.metric and cloud.trained and len(cloud.points) == int(kept.sum())
    rows, columns = np.nonzero(kept)  # the points are the kept pixels in row-major order
    np.testing.assert_allclose(cloud.points[:, 2], maps.depth[kept], rtol=1e-6)
    np.testing.assert_allclose(cloud.points[:, 0], columns * maps.depth[kept] / 500.0, rtol=1e-5)
    np.testing.assert_array_equal(cloud.colors, left[kept])
    vertex = PlyData.read(io.BytesIO(cloud.ply))["vertex"]  # the file, as any PLY reader sees it
    np.testing.assert_array_equal(np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1), cloud.points)
    certain = kept & (maps.uncertainty <= 0.001)
    assert not image_space.metric and 0 < len(image_space.points) < len(cloud.points)
    np.testing.assert_array_equal(image_space.points[:, 2], maps.disparity[certain])


def test_depth_bounds_and_a_deadline_reach_the_service(default_server):
    right, left = stereo_pair()  # disparities about 4 px
    rig = {"focal_px": 500.0, "baseline_m": 0.12}
    with StereoClient(default_server.base_url) as service:
        everything = service.disparity(left, right, deadline_ms=60_000, **rig)
        assert everything.depth is not None
        limit = float(np.median(everything.depth))
        bounded = service.disparity(left, right, max_depth_m=limit, min_disparity=0.5, **rig)
        with pytest.raises(ServiceError) as too_soon:
            service.disparity(left, right, deadline_ms=5)  # under the service's least deadline: refused at once
    assert bounded.depth is not None
    deeper = everything.depth > limit
    assert 0 < deeper.mean() < 1 and np.isinf(bounded.depth[deeper]).all()
    np.testing.assert_array_equal(bounded.depth[~deeper], everything.depth[~deeper])
    assert (too_soon.value.status, too_soon.value.code) == (503, "deadline_exceeded")


def test_a_mistyped_option_is_refused_before_anything_is_sent():
    left, right = stereo_pair()
    with StereoClient("http://127.0.0.1:9") as nowhere:  # nothing listens: a request sent would fail otherwise
        with pytest.raises(TypeError, match="unknown option 'flp'.*flip"):
            nowhere.disparity(left, right, flp=True)  # type: ignore[call-arg]
        with pytest.raises(TypeError, match="unknown option 'warm_iter'"):
            nowhere.stream(warm_iter=3)  # type: ignore[call-arg]


def test_an_address_without_http_or_https_is_refused_at_once_naming_the_form():
    for client in (StereoClient, AsyncStereoClient):
        with pytest.raises(
            ValueError, match=r"localhost:8000: .* http:// or https:// \(for example http://localhost:8000\)"
        ):
            client("localhost:8000")
        with pytest.raises(ValueError, match="ftp://host: the service's address starts with http:// or https://$"):
            client("ftp://host")


class WebPage(BaseHTTPRequestHandler):
    """Another server at the address: a web page for every GET and POST."""

    def answer(self) -> None:
        self.rfile.read(int(self.headers.get("Content-Length") or 0))
        page = b"<html><body>a web page</body></html>"
        self.send_response(200)
        self.send_header("Content-Type", "text/html")
        self.send_header("Content-Length", str(len(page)))
        self.end_headers()
        self.wfile.write(page)

    do_GET = do_POST = answer

    def log_message(self, *_: object) -> None:
        pass


def test_another_server_at_the_address_is_named_as_not_the_service():
    server = ThreadingHTTPServer(("127.0.0.1", 0), WebPage)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        with StereoClient(f"http://127.0.0.1:{server.server_port}", max_retries=0) as client:
            errors = []
            for call in (lambda: client.disparity(*stereo_pair()), client.health):
                with pytest.raises(ServiceError) as refused:
                    call()
                errors.append(refused.value)
    finally:
        server.shutdown()
    for error in errors:
        assert error.code == "not_a_service" and "answered text/html" in error.message
        assert "is this the address of a crestereo-pp service?" in error.message


def test_a_result_carries_the_row_offset_the_service_measured_from_headers_and_from_a_stream(default_server):
    sample = small_dev_sample()  # Tsukuba, its right image moved 1.5 px down
    height, width = sample.left.shape[:2]
    down = cv2.warpAffine(sample.right, np.float32([[1, 0, 0], [0, 1, 1.5]]), (width, height))
    fast: Options = {"two_pass": False, "iters": (1, 1, 1)}
    with StereoClient(default_server.base_url) as service:
        result = service.disparity(sample.left, down, **fast)
        unaligned = service.disparity(sample.left, down, align_rows=False, **fast)
        with service.stream(**fast) as frames:
            streamed = frames.send(sample.left, down)
    assert isinstance(result.row_offset, RowOffset)
    assert result.row_offset.centre_px == pytest.approx(1.5, abs=0.1) and result.row_offset.aligned
    assert result.row_offset.tracks >= 100 and isinstance(result.row_offset.tracks, int)
    assert streamed.row_offset == result.row_offset
    assert unaligned.row_offset is None


@pytest.mark.anyio
async def test_the_async_client_gives_the_same_answer(default_server):
    left, right = stereo_pair()
    async with AsyncStereoClient(default_server.base_url) as service:
        result = await service.disparity(left, right)
        flipped = await service.disparity(left, right, flip=True)
        cloud = await service.point_cloud(left, right, focal_px=500.0, baseline_m=0.12)
        with pytest.raises(ServiceError):
            await service.disparity(left, right[:, :-1])
    with StereoClient(default_server.base_url) as service:
        np.testing.assert_array_equal(result.disparity, service.disparity(left, right).disparity)
        np.testing.assert_array_equal(flipped.disparity, service.disparity(left, right, flip=True).disparity)
        again = service.point_cloud(left, right, focal_px=500.0, baseline_m=0.12)
        np.testing.assert_array_equal(cloud.points, again.points)
        np.testing.assert_array_equal(cloud.colors, again.colors)
    direct = quiet_load_model("lite").predict(left, right, flip=True)
    np.testing.assert_allclose(flipped.disparity, direct.disparity, rtol=1e-4, atol=1e-3)
    assert np.abs(flipped.disparity - result.disparity).max() > 0.1  # the option reached the service


@pytest.mark.slow
def test_a_full_queue_is_retried_after_retry_after_until_served(tmp_path):
    left, right = stereo_pair(96, 128)
    with run_uvicorn(tmp_path, max_queue="1", max_batch_size="1") as server:
        patient = StereoClient(server.base_url, max_retries=20, max_retry_wait_s=2)
        impatient = StereoClient(server.base_url, max_retries=0)
        outcomes: list[object] = []

        def post(client: StereoClient) -> None:
            try:
                outcomes.append(client.disparity(left, right))
            except ServiceError as error:
                outcomes.append(error)

        threads = [threading.Thread(target=post, args=(patient,)) for _ in range(4)]
        threads += [threading.Thread(target=post, args=(impatient,)) for _ in range(4)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=120)
    refused = [o for o in outcomes if isinstance(o, ServiceError)]
    assert len(outcomes) == 8
    assert all(error.code == "queue_full" and error.retry_after is not None for error in refused)
    assert refused, "the burst never filled the queue: nothing was retried"
    served = [o for o in outcomes if not isinstance(o, ServiceError)]
    assert len(served) >= 4  # every patient request, however often refused, was served in the end


def test_a_stream_the_service_ends_raises_service_error_saying_why(default_server):
    (left, right), _ = panned_frames(2, width=96, seed=7, step_px=3.0)
    with StereoClient(default_server.base_url) as service, pytest.raises(ServiceError) as refused:
        with service.stream(scale=2) as stream:
            time.sleep(0.5)  # the service has closed it: the pair's images meet a closed connection
            stream.send(left, right)

    async def send_on_a_closed_stream() -> None:
        async with AsyncStereoClient(default_server.base_url) as service, service.stream(scale=2) as stream:
            await asyncio.sleep(0.5)
            await stream.send(left, right)

    with pytest.raises(ServiceError) as async_refused:
        asyncio.run(send_on_a_closed_stream())
    for error in (refused.value, async_refused.value):
        assert (error.status, error.code) == (0, "invalid_request") and "scale" in error.message


def test_a_stream_the_service_closed_for_being_idle_is_opened_again_by_the_next_pair(tmp_path):
    frames = panned_frames(2, width=96, seed=7, step_px=3.0)
    fast: Options = {"iters": (1, 1, 2), "two_pass": False}
    with run_uvicorn(tmp_path, stream_idle_timeout_s="1") as server, StereoClient(server.base_url) as service:
        with service.stream(**fast) as stream:
            stream.send(*frames[0])
            time.sleep(2.5)  # past the service's idle timeout: it closes the stream
            after_a_pause = stream.send(*frames[1])
            then = stream.send(*frames[1])

        async def pause_then_send() -> tuple[DisparityResult, DisparityResult]:
            async with AsyncStereoClient(server.base_url) as service, service.stream(**fast) as stream:
                await stream.send(*frames[0])
                await asyncio.sleep(2.5)
                return await stream.send(*frames[1]), await stream.send(*frames[1])

        async_after_a_pause, _ = asyncio.run(pause_then_send())
        cold = service.disparity(*frames[1], **fast)  # a new stream's first pair is computed cold
    for result in (after_a_pause, async_after_a_pause):
        np.testing.assert_allclose(result.disparity, cold.disparity, atol=1e-3)
    assert not np.allclose(then.disparity, cold.disparity, atol=1e-3)  # warm-started from the pair before
