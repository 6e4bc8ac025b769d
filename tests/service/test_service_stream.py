"""`/disparity/stream` over a real WebSocket on a real uvicorn: the pairs of one camera answered in
order, each warm-started from the previous one as the library computes a sequence; a bad frame
answered with an error while the stream goes on; protocol errors, bad options and a missing key
refused with a clear message and close code; the client's `stream`."""

from __future__ import annotations

import asyncio
import io
import json

import httpx
import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from crestereo_pp.client import AsyncStereoClient, ServiceError, StereoClient
from crestereo_pp.inference import InferenceOptions
from panned_frames import panned_frames
from service_helpers import (
    assert_same_maps,
    cornered_pair,
    decode_array,
    encode,
    pair_files,
    quiet_load_model,
    run_uvicorn,
    stereo_pair,
    ws_url,
)


def test_a_stream_answers_each_pair_in_order_warm_started_as_the_library_computes_a_sequence(default_server):
    frames = panned_frames(3, width=96, seed=7, step_px=3.0)
    with StereoClient(default_server.base_url) as service, service.stream(iters=(1, 1, 2), warm_iters=3) as stream:
        results = [stream.send(left, right) for left, right in frames]
    expected = list(quiet_load_model("lite").predict_sequence(frames, InferenceOptions(iters=(1, 1, 2)), warm_iters=3))
    for result, reference in zip(results, expected, strict=True):
        assert result.model == "lite" and result.trained and result.disparity.shape == (64, 96)
        assert_same_maps(result.disparity, reference.disparity)


@pytest.mark.anyio
async def test_the_async_client_streams_the_same_maps_and_goes_on_past_a_bad_frame(default_server):
    frames = panned_frames(3, width=96, seed=7, step_px=3.0)
    with StereoClient(default_server.base_url) as service, service.stream(iters=(1, 1, 2), warm_iters=3) as stream:
        expected = [stream.send(left, right) for left, right in frames]
    async with AsyncStereoClient(default_server.base_url) as service:
        async with service.stream(iters=(1, 1, 2), warm_iters=3) as async_stream:
            results = [await async_stream.send(left, right) for left, right in frames]
            with pytest.raises(ServiceError) as bad_frame:
                await async_stream.send(b"not an image", frames[0][1])
            after = await async_stream.send(*frames[0])
    for result, reference in zip(results, expected, strict=True):
        np.testing.assert_array_equal(result.disparity, reference.disparity)
    assert bad_frame.value.code == "unsupported_media_type"
    assert after.disparity.shape == frames[0][0].shape[:2] and after.trained


def test_a_bad_frame_gets_an_error_naming_it_and_the_stream_goes_on(default_server):
    (left, right), (next_left, next_right) = panned_frames(2, width=96, seed=7, step_px=3.0)
    with connect(ws_url(default_server.base_url, "format=npz")) as socket:
        socket.send(b"not an image")
        socket.send(encode(right))
        error = json.loads(socket.recv(timeout=60))
        socket.send(encode(left))
        socket.send(encode(next_right[:, :-1]))  # of another size than its left image
        mismatch = json.loads(socket.recv(timeout=60))
        socket.send(encode(next_left))
        socket.send(encode(next_right))
        answer = socket.recv(timeout=60)
    assert error == {
        "error": {"code": "unsupported_media_type", "message": "left: not a PNG, JPEG, BMP or TIFF file"},
        "frame": 0,
    }
    assert mismatch["frame"] == 1 and mismatch["error"]["code"] == "size_mismatch"
    assert isinstance(answer, bytes) and answer.startswith(b"PK")  # an npz archive


def test_a_binary_frame_carries_inside_its_file_the_facts_a_json_frame_gives(default_server):
    left, right = cornered_pair()
    answers = {}
    for format in ("json", "npz"):
        with connect(ws_url(default_server.base_url, f"format={format}")) as socket:
            socket.send(encode(left))
            socket.send(encode(right))
            answers[format] = socket.recv(timeout=60)
    assert isinstance(answers["json"], str) and isinstance(answers["npz"], bytes)
    body = json.loads(answers["json"])
    archive = np.load(io.BytesIO(answers["npz"]))
    facts = json.loads(str(archive["facts"]))
    assert facts["row_offset"] is not None and facts["timings"]["compute_ms"] > 0
    # the same facts but the timings (each stream computed the pair on its own)
    said = {name: value for name, value in body.items() if name not in ("disparity", "uncertainty", "depth", "timings")}
    assert {name: value for name, value in facts.items() if name != "timings"} == said
    assert_same_maps(archive["disparity"], decode_array(body["disparity"]))


def test_a_pair_asking_for_more_compute_than_one_request_may_is_refused_and_the_stream_goes_on(default_server):
    # 45 iterations at 1/4 cost 4.25 plain requests of the pair's size; lite's largest image is
    # 2048x2048, and the default limit is 4 of those.
    flat = encode(np.full((2048, 2048, 3), 128, np.uint8))
    ((left, right),) = panned_frames(1, width=96, seed=7, step_px=3.0)
    with connect(ws_url(default_server.base_url, "format=npz&iters=45")) as socket:
        socket.send(flat)
        socket.send(flat)
        refused = json.loads(socket.recv(timeout=60))
        socket.send(encode(left))
        socket.send(encode(right))
        answer = socket.recv(timeout=60)
    assert refused["frame"] == 0 and refused["error"]["code"] == "request_too_costly"
    assert isinstance(answer, bytes) and answer.startswith(b"PK")


def test_protocol_errors_and_bad_options_close_the_stream_saying_why(default_server):
    with connect(ws_url(default_server.base_url)) as socket:
        socket.send("hello")  # text where the left image is expected
        said = json.loads(socket.recv(timeout=30))
        with pytest.raises(ConnectionClosed):
            socket.recv(timeout=30)
    assert said["error"]["code"] == "invalid_message" and "binary message" in said["error"]["message"]
    assert socket.close_code == 1003
    for query, expected in (
        ("scale=2", "query.scale"),
        ("warm_iters=0", "query.warm_iters"),
        ("frame=original", "frame=original"),
    ):
        with connect(ws_url(default_server.base_url, query)) as socket:
            said = json.loads(socket.recv(timeout=30))
            with pytest.raises(ConnectionClosed):
                socket.recv(timeout=30)
        assert said["error"]["code"] == "invalid_request" and expected in said["error"]["message"], query
        assert socket.close_code == 1008


def test_a_stream_refuses_a_bad_option_in_the_words_post_disparity_uses(default_server):
    messages, files = {}, pair_files(*stereo_pair())
    for query in (
        "iters=1000000",
        "two_pass=maybe",
        "bogus=1",
        "scale=2",
        "flip=x",
        "min_disparity=5",
        "focal_px=700",
        "iters=0&scale=0",
    ):
        with connect(ws_url(default_server.base_url, query)) as socket:
            said = json.loads(socket.recv(timeout=30))
        answer = httpx.post(f"{default_server.base_url}/disparity?{query}", files=files, timeout=60)
        messages[query] = (said["error"]["message"], answer.json()["error"]["message"])
    for query, (streamed, posted) in messages.items():
        # a stream says why a depth limit cannot apply as a request does, and adds that its pairs are rectified
        assert streamed in (posted, f"{posted}; a stream's pairs are rectified"), query
    assert messages["bogus=1"][0].startswith("query.bogus: unknown option; the options are model, format,")


def test_a_stream_needs_the_bearer_key_when_the_server_has_one(tmp_path):
    left, right = panned_frames(1, width=96, seed=7, step_px=3.0)[0]
    with run_uvicorn(tmp_path, api_key="s3cret") as server:
        with pytest.raises(InvalidStatus) as refused, connect(ws_url(server.base_url)):
            pass
        with pytest.raises(ServiceError) as client_refused, StereoClient(server.base_url, api_key="wrong") as service:
            service.stream()
        with StereoClient(server.base_url, api_key="s3cret") as service, service.stream() as stream:
            result = stream.send(left, right)

        async def open_async_stream() -> None:
            async with AsyncStereoClient(server.base_url, api_key="wrong") as service, service.stream():
                pass

        with pytest.raises(ServiceError) as async_refused:
            asyncio.run(open_async_stream())
    # refused at the handshake, with the service's JSON error (the connection never opens)
    assert refused.value.response.status_code == 403
    assert json.loads(refused.value.response.body)["error"]["code"] == "unauthorized"
    assert client_refused.value.status == 403 and client_refused.value.code == "unauthorized"
    assert (async_refused.value.status, async_refused.value.code) == (403, "unauthorized")
    assert result.disparity.shape == left.shape[:2]
