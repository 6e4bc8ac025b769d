"""Attacks that once took the server down, each against a real uvicorn process on loopback."""

from __future__ import annotations

import base64
import hashlib
import json
import os
import re
import socket
import struct
import subprocess
import sys
import time
import zlib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import cv2
import httpx
import numpy as np
import pytest

from crestereo_pp.service.__main__ import SERVER_LIMITS
from crestereo_pp.service.uploads.images import ImageError, read_header
from service_helpers import REPO, encode, metric_total, pair_files, read_answer, run_uvicorn, stereo_pair


def tiff_with_repeated_size_tags(first: int, second: int) -> bytes:
    """A little-endian TIFF whose first IFD holds each size tag twice: `first`, then `second`.
    libtiff takes the first, a naive header parser the last."""
    entries = [
        (256, 3, 1, first),
        (256, 3, 1, second),
        (257, 3, 1, first),
        (257, 3, 1, second),
        (258, 3, 1, 8),
        (259, 3, 1, 1),
        (262, 3, 1, 1),
        (273, 4, 1, 200),
        (278, 3, 1, second),
        (279, 4, 1, second * second),
    ]
    ifd = (
        struct.pack("<H", len(entries))
        + b"".join(struct.pack("<HHII", tag, kind, count, value) for tag, kind, count, value in entries)
        + b"\0" * 4
    )
    header = b"II*\x00" + struct.pack("<I", 8)
    body = header + ifd
    return body + b"\0" * (200 - len(body)) + b"\x80" * (second * second)


def jpeg_with_fill_bytes(fill: int) -> bytes:
    """SOI, `fill` fill bytes, then a 64x64 baseline frame header (no scan: the header is enough)."""
    sof = b"\xff\xc0" + struct.pack(">HBHHB", 11, 8, 64, 64, 1) + b"\x01\x11\x00"
    return b"\xff\xd8" + b"\xff" * fill + sof + b"\xff\xd9"


def tiff(entries: list[tuple[int, int, int, int]], payload: bytes = b"") -> bytes:
    """A little-endian TIFF of one IFD with these (tag, type, count, value) entries, then `payload`."""
    ifd = (
        struct.pack("<H", len(entries))
        + b"".join(struct.pack("<HHII", tag, kind, count, value) for tag, kind, count, value in entries)
        + b"\0" * 4
    )
    return b"II*\x00" + struct.pack("<I", 8) + ifd + payload


def tiff_tile_bomb(side: int = 64, tile: int = 16_000) -> bytes:
    """A `side` x `side` Deflate TIFF whose only tile is `tile` x `tile` pixels: a decoder that
    trusts the tile tags allocates the whole tile (16000^2 x 3 bytes: 0.77 GB) for a tiny image."""
    payload = zlib.compress(b"\0" * 1_000_000, 9)
    offset = 8 + 2 + 12 * 10 + 4
    return tiff(
        [
            (256, 3, 1, side),
            (257, 3, 1, side),
            (258, 3, 1, 8),
            (259, 3, 1, 8),  # Deflate
            (262, 3, 1, 1),
            (277, 3, 1, 1),
            (322, 4, 1, tile),
            (323, 4, 1, tile),
            (324, 4, 1, offset),
            (325, 4, 1, len(payload)),
        ],
        payload,
    )


def jpeg_with_scans(scans: int) -> bytes:
    """A progressive 64x64 JPEG whose last scan is repeated until the file has `scans` scans: each
    scan makes the decoder sweep the whole image once."""
    image = np.random.default_rng(0).integers(0, 256, (64, 64, 3), dtype=np.uint8)
    data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1].tobytes()
    last_scan = data[data.rindex(b"\xff\xda") : -2]
    return data[:-2] + last_scan * (scans - data.count(b"\xff\xda")) + b"\xff\xd9"


def test_a_tiff_whose_tiles_dwarf_the_image_is_refused_from_its_header():
    assert read_header(tiff_tile_bomb(tile=64)).width == 64  # tiles the size of the image are fine
    with pytest.raises(ImageError, match="tiles of 16000 px"):
        read_header(tiff_tile_bomb())


def test_a_jpeg_of_many_scans_is_refused_from_its_header_in_linear_time():
    assert read_header(jpeg_with_scans(12)).width == 64  # progressive encoders write about a dozen
    started = time.perf_counter()
    with pytest.raises(ImageError, match="scans"):
        read_header(jpeg_with_scans(20_000))
    assert time.perf_counter() - started < 0.5


@pytest.mark.parametrize(
    "data",
    [
        cv2.imencode(".tiff", np.zeros((40, 40), np.float32))[1].tobytes(),
        tiff([(256, 3, 1, 40), (257, 3, 1, 40), (258, 3, 1, 16), (339, 3, 1, 2)]),  # signed 16-bit
        b"\xff\xd8\xff\xc0" + struct.pack(">HBHHB", 11, 12, 40, 40, 1) + b"\x01\x11\x00\xff\xd9",  # 12-bit
    ],
    ids=["float32-tiff", "int16-tiff", "12-bit-jpeg"],
)
def test_sample_formats_the_service_does_not_read_are_unsupported_not_broken(data):
    with pytest.raises(ImageError) as refused:
        read_header(data)
    assert refused.value.unsupported  # answered 415, as the README promises


def test_a_tiff_with_repeated_size_tags_is_refused_from_its_header():
    with pytest.raises(ImageError, match="repeated tag"):
        read_header(tiff_with_repeated_size_tags(20_000, 64))


def test_the_jpeg_marker_walk_is_bounded_whatever_the_file_holds():
    assert read_header(jpeg_with_fill_bytes(3)).width == 64  # a few fill bytes are legal
    started = time.perf_counter()
    with pytest.raises(ImageError, match="fill bytes"):
        read_header(jpeg_with_fill_bytes(16_000_000))
    many_segments = b"\xff\xd8" + b"\xff\xe1\x00\x02" * 100_000 + jpeg_with_fill_bytes(0)[2:]
    with pytest.raises(ImageError, match="frame header"):
        read_header(many_segments)
    assert time.perf_counter() - started < 0.5


@pytest.mark.slow
def test_the_decoder_itself_is_capped_at_the_services_pixel_limit():
    """OpenCV refuses to decode beyond CRESTEREO_MAX_IMAGE_PIXELS once `service` is imported,
    whatever the file header claims (a fresh process: OpenCV reads the cap at its first decode)."""
    script = (
        "import service, cv2, numpy as np\n"
        "from stereo_data.formats import FormatError, decode_image\n"
        "ok = cv2.imencode('.png', np.zeros((30, 30, 3), np.uint8))[1].tobytes()\n"
        "big = cv2.imencode('.png', np.zeros((40, 40, 3), np.uint8))[1].tobytes()\n"
        "print(decode_image(ok).shape == (30, 30, 3))\n"
        "try:\n"
        "    decode_image(big)\n"
        "except FormatError as error:\n"
        "    print('pixel limit' in str(error))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "OPENCV_IO_MAX_IMAGE_PIXELS"}
    result = subprocess.run(
        [sys.executable, "-c", script],
        cwd=REPO,
        capture_output=True,
        text=True,
        env={**env, "CRESTEREO_MAX_IMAGE_PIXELS": "1000"},
        check=True,
    )
    assert result.stdout.split() == ["True", "True"]


def test_crafted_uploads_get_422_fast_and_never_stall_the_health_check(default_server):
    _, right = stereo_pair()
    attacks = [
        {
            "left": ("l.tif", tiff_with_repeated_size_tags(20_000, 64), "image/tiff"),
            "right": ("r.png", encode(right), "image/png"),
        },
        {
            "left": ("l.jpg", jpeg_with_fill_bytes(16_000_000), "image/jpeg"),
            "right": ("r.png", encode(right), "image/png"),
        },
        {"left": ("l.tif", tiff_tile_bomb(), "image/tiff"), "right": ("r.png", encode(right), "image/png")},
        {"left": ("l.jpg", jpeg_with_scans(20_000), "image/jpeg"), "right": ("r.png", encode(right), "image/png")},
    ] * 2
    with httpx.Client(base_url=default_server.base_url, timeout=60) as client, ThreadPoolExecutor(4) as pool:
        memory_before = metric_total(client.get("/metrics").text, "process_resident_memory_bytes")
        answers = pool.map(lambda files: client.post("/disparity", files=files), attacks)
        live_seconds = []
        for _ in range(20):
            started = time.perf_counter()
            assert client.get("/health/live").status_code == 200
            live_seconds.append(time.perf_counter() - started)
            time.sleep(0.05)
        answers = list(answers)
        memory_after = metric_total(client.get("/metrics").text, "process_resident_memory_bytes")
    assert [(a.status_code, a.json()["error"]["code"]) for a in answers] == [(422, "undecodable_image")] * 8
    assert memory_after - memory_before < 200e6  # a tile bomb once added 0.9 GB per image
    assert max(live_seconds) < 1.0, live_seconds


def test_a_client_gone_mid_upload_counts_as_499_without_a_traceback(default_server):
    before = httpx.get(default_server.base_url + "/metrics").text
    host, port = default_server.base_url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port))) as sock:
        sock.sendall(
            b"POST /disparity HTTP/1.1\r\nHost: x\r\nContent-Length: 1000000\r\n"
            b"Content-Type: multipart/form-data; boundary=b\r\n\r\n"
            b'--b\r\nContent-Disposition: form-data; name="left"; filename="l.png"\r\n\r\n' + b"\0" * 50_000
        )
        time.sleep(0.3)
    deadline = time.monotonic() + 10
    while True:
        after = httpx.get(default_server.base_url + "/metrics").text
        if (
            metric_total(after, "crestereo_requests_total", status="499")
            > metric_total(before, "crestereo_requests_total", status="499")
            or time.monotonic() > deadline
        ):
            break
        time.sleep(0.1)
    assert (
        metric_total(after, "crestereo_requests_total", status="499")
        == metric_total(before, "crestereo_requests_total", status="499") + 1
    )
    assert metric_total(after, "crestereo_requests_total", status="500") == metric_total(
        before, "crestereo_requests_total", status="500"
    )
    assert "Traceback" not in default_server.log() and "ClientDisconnect" not in default_server.log()


@pytest.mark.parametrize("size", [20_000, 500_000])
def test_oversized_request_headers_get_a_json_431_and_the_server_stays_up(default_server, size):
    response = httpx.post(default_server.base_url + "/disparity", headers={"X-Big": "a" * size})
    assert response.status_code == 431
    assert response.json()["error"]["code"] == "headers_too_large"
    assert httpx.get(default_server.base_url + "/health/live").status_code == 200


def test_a_request_head_past_uvicorns_limit_gets_a_json_400_and_the_server_stays_up(default_server):
    # An unfinished head one byte past h11_max_incomplete_event_size (512 KiB, so that 2048
    # connections' heads hold at most 1 GiB): the server's protocol answers it (400
    # `malformed_request`) before the app sees the request. One byte past, so that it is all read
    # first: the server closes with nothing unread.
    limit = SERVER_LIMITS["h11_max_incomplete_event_size"]
    head = b"POST /disparity HTTP/1.1\r\nHost: x\r\nX-Big: "
    host, port = default_server.base_url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port))) as sock:
        sock.sendall(head + b"a" * (limit + 1 - len(head)))
        sock.settimeout(10)
        answer = b""
        while chunk := sock.recv(65536):
            answer += chunk
    head_part, _, body = answer.partition(b"\r\n\r\n")
    assert limit == 512 * 1024 and head_part.startswith(b"HTTP/1.1 400") and b"application/json" in head_part
    assert json.loads(body)["error"]["code"] == "malformed_request"
    assert httpx.get(default_server.base_url + "/health/live").status_code == 200


def live_seconds_while(work: Callable[[], list[httpx.Response]], base_url: str) -> tuple[list[httpx.Response], float]:
    """Run `work` in a thread while probing `/health/live`: its answers and the slowest probe (s)."""
    with httpx.Client(base_url=base_url, timeout=10) as client, ThreadPoolExecutor(1) as pool:
        answers = pool.submit(work)
        slowest = 0.0
        while not answers.done():
            started = time.perf_counter()
            assert client.get("/health/live").status_code == 200
            slowest = max(slowest, time.perf_counter() - started)
            time.sleep(0.05)
        return answers.result(), slowest


def test_a_query_flood_gets_a_json_414_at_once(default_server):
    flood = b"scale=1&" * 48_000  # 384 KB of one option repeated: once 19 s on the event loop
    host, port = default_server.base_url.removeprefix("http://").split(":")
    started = time.perf_counter()
    with socket.create_connection((host, int(port))) as sock:
        sock.sendall(b"POST /disparity?" + flood + b" HTTP/1.1\r\nHost: x\r\nContent-Length: 0\r\n\r\n")
        answer = read_answer(sock)
    assert answer.startswith("HTTP/1.1 414") and '"query_too_long"' in answer
    assert time.perf_counter() - started < 1.0


def test_options_given_twice_are_refused_by_name(default_server):
    left, right = stereo_pair()
    files = {"left": ("l.png", encode(left), "image/png"), "right": ("r.png", encode(right), "image/png")}
    url = default_server.base_url + "/disparity"
    twice = httpx.post(url + "?model=lite&model=lite", files=files)
    assert twice.status_code == 422 and "query.model: given more than once" in twice.json()["error"]["message"]
    headers = [("X-Request-Timeout-Ms", "5000"), ("X-Request-Timeout-Ms", "10")]
    twice = httpx.post(url, files=files, headers=headers)
    assert twice.status_code == 422 and "X-Request-Timeout-Ms" in twice.json()["error"]["message"]
    many = httpx.post(url + "?" + "&".join(f"unknown{i}=1" for i in range(300)), files=files)
    assert many.status_code == 422 and many.json()["error"]["message"].endswith("and 295 more")


@pytest.mark.parametrize("scale", ["0.05", "1e-300"])
def test_a_scale_that_leaves_the_network_too_few_pixels_is_refused(default_server, scale):
    left, right = stereo_pair(height=64, width=256)
    files = {"left": ("l.png", encode(left), "image/png"), "right": ("r.png", encode(right), "image/png")}
    response = httpx.post(default_server.base_url + f"/disparity?scale={scale}", files=files)
    assert response.status_code == 422 and response.json()["error"]["code"] == "scale_too_small"


def test_a_few_kb_asking_for_many_times_the_largest_plain_compute_is_refused_before_it_is_computed(default_server):
    # Two flat 2048x2048 PNGs (lite's largest image) with 99 iterations a stage and flip: computed,
    # they held the one inference thread for 889 s on a 2-core CPU (14.9 s with the defaults).
    flat = encode(np.full((2048, 2048, 3), 128, np.uint8))
    assert len(flat) < 64 * 1024
    url = default_server.base_url + "/disparity"
    computed_before = computed_pairs(default_server.base_url)
    costly = httpx.post(
        url + "?iters=99,99,99&flip=true", files={"left": ("l.png", flat), "right": ("r.png", flat)}, timeout=60
    )
    assert costly.status_code == 422
    error = costly.json()["error"]
    assert error["code"] == "request_too_costly"
    assert "(2048x2048)" in error["message"] and "29.5 times a plain request" in error["message"]
    assert "allows 4:" in error["message"]
    assert computed_pairs(default_server.base_url) == computed_before
    left, right = stereo_pair()
    plain = httpx.post(url, files={"left": ("l.png", encode(left)), "right": ("r.png", encode(right))}, timeout=60)
    assert plain.status_code == 200
    assert computed_pairs(default_server.base_url) == computed_before + 1


def computed_pairs(base_url: str) -> float:
    """Pairs the server has computed (the sum of its batch sizes), from `/metrics`."""
    return metric_total(httpx.get(base_url + "/metrics").text, "crestereo_batch_size_sum", model="lite")


@pytest.mark.parametrize("scale", ["nan", "1_0", "inf", "0x1p-3"])
def test_numbers_in_the_query_are_plain_decimals(default_server, scale):
    left, right = stereo_pair()
    files = {"left": ("l.png", encode(left), "image/png"), "right": ("r.png", encode(right), "image/png")}
    response = httpx.post(default_server.base_url + f"/disparity?scale={scale}", files=files)
    assert response.status_code == 422 and "expected a decimal number" in response.json()["error"]["message"]


@pytest.mark.parametrize("path", ["/", "/metrics", "/models", "/models/lite", "/static/app.js"])
def test_head_is_answered_wherever_get_is(default_server, path):
    assert httpx.head(default_server.base_url + path).status_code == 200


@pytest.mark.slow
def test_an_upload_that_stalls_gets_408_and_frees_its_place(tmp_path):
    with run_uvicorn(tmp_path, body_timeout_s="1") as server:
        host, port = server.base_url.removeprefix("http://").split(":")
        with socket.create_connection((host, int(port))) as sock:
            sock.sendall(
                b"POST /disparity HTTP/1.1\r\nHost: x\r\nContent-Length: 1000000\r\n"
                b"Content-Type: multipart/form-data; boundary=b\r\n\r\n" + b"\0" * 50_000
            )
            started = time.monotonic()
            answer = read_answer(sock)
            waited = time.monotonic() - started
        metrics = httpx.get(server.base_url + "/metrics").text
    assert answer.startswith("HTTP/1.1 408") and '"body_timeout"' in answer
    assert 0.8 < waited < 5
    assert metric_total(metrics, "crestereo_requests_total", status="408") == 1


@pytest.mark.slow
def test_floods_of_connections_and_uploads_never_lock_out_the_probes(tmp_path):
    with run_uvicorn(tmp_path, max_requests="2") as server:
        host, port = server.base_url.removeprefix("http://").split(":")
        idle = [socket.create_connection((host, int(port))) for _ in range(200)]  # once over uvicorn's cap
        stalled = []
        try:
            for _ in range(2):  # two uploads in progress, the most this server takes at once
                sock = socket.create_connection((host, int(port)))
                sock.sendall(
                    b"POST /disparity HTTP/1.1\r\nHost: x\r\nContent-Length: 1000000\r\n"
                    b"Content-Type: multipart/form-data; boundary=b\r\n\r\n" + b"\0" * 1000
                )
                stalled.append(sock)
            time.sleep(0.3)
            live = httpx.get(server.base_url + "/health/live", timeout=5)
            ready = httpx.get(server.base_url + "/health/ready", timeout=5)
            refused = httpx.post(server.base_url + "/disparity", content=b"x", timeout=5)
        finally:
            for sock in idle + stalled:
                sock.close()
        time.sleep(0.3)
        left, right = stereo_pair()
        files = {"left": ("l.png", encode(left), "image/png"), "right": ("r.png", encode(right), "image/png")}
        served = httpx.post(server.base_url + "/disparity", files=files, timeout=60)
    assert live.status_code == 200 and ready.status_code == 200
    assert refused.status_code == 503 and refused.json()["error"]["code"] == "overloaded"
    assert int(refused.headers["Retry-After"]) >= 1
    assert served.status_code == 200  # and the places come back once the uploads go


def test_multipart_padding_is_refused_quickly_and_parsed_away_from_the_event_loop(default_server):
    left, right = stereo_pair()
    body = (
        b'--b\r\nContent-Disposition: form-data; name="left"; filename="l.png"\r\n\r\n'
        + encode(left)
        + b"\r\n--b"
        + b" " * (20 << 20)  # 20 MiB after a boundary: python-multipart walks it byte by byte (4.6 s here)
        + b'\r\nContent-Disposition: form-data; name="right"; filename="r.png"\r\n\r\n'
        + encode(right)
        + b"\r\n--b--\r\n"
    )
    headers = {"Content-Type": "multipart/form-data; boundary=b"}

    def flood() -> list[httpx.Response]:
        with ThreadPoolExecutor(4) as pool:
            posts = [
                pool.submit(
                    httpx.post, default_server.base_url + "/disparity", content=body, headers=headers, timeout=60
                )
                for _ in range(4)
            ]
            return [post.result() for post in posts]

    started = time.perf_counter()
    answers, slowest = live_seconds_while(flood, default_server.base_url)
    assert [(a.status_code, a.json()["error"]["code"]) for a in answers] == [(422, "invalid_multipart")] * 4
    assert slowest < 1.0
    assert time.perf_counter() - started < 10


def test_the_docs_page_runs_only_the_packaged_script_it_names_and_its_hashed_inline_one(default_server):
    page = httpx.get(default_server.base_url + "/docs")
    policy = page.headers["Content-Security-Policy"]
    scripts = re.findall(r"<script([^>]*)>(.*?)</script>", page.text, flags=re.S)
    external = [attributes for attributes, _ in scripts if "src=" in attributes]
    inline = [body for attributes, body in scripts if "src=" not in attributes]
    assert external == [' src="static/docs/swagger-ui-bundle.js"']  # this server's copy, pinned by its sha256
    for body in inline:  # each inline script is allowed by its own hash, and nothing else inline is
        digest = base64.b64encode(hashlib.sha256(body.encode()).digest()).decode()
        assert f"'sha256-{digest}'" in policy
    assert "default-src 'none'" in policy and "'unsafe-inline'" not in policy.split("script-src")[1].split(";")[0]
    assert httpx.get(default_server.base_url + "/redoc").status_code == 404


def test_a_client_repeating_bad_requests_gets_its_errors_paced_and_good_answers_are_not_held(tmp_path):
    missing_right = {"left": ("l.png", encode(stereo_pair()[0]), "image/png")}
    with run_uvicorn(tmp_path, client_error_rate="4", client_error_burst="3", max_requests="1") as server:
        with httpx.Client(base_url=server.base_url, timeout=30) as client:
            # a first good pair warms the server up (its decoders start on the first upload); a
            # successful answer is never paced and takes nothing from the error budget
            assert client.post("/disparity", files=pair_files(*stereo_pair())).status_code == 200
            seconds = []
            for _ in range(7):
                started = time.perf_counter()
                answer = client.post("/disparity", files=missing_right)
                seconds.append(time.perf_counter() - started)
                assert answer.status_code == 422 and answer.json()["error"]["code"] == "missing_field"
            # the burst at once, then about 1 / rate each
            assert max(seconds[:3]) < 0.2, seconds
            assert all(0.15 <= s < 0.6 for s in seconds[3:]), seconds
            assert sum(seconds[3:]) >= 0.75  # four errors past the burst: about one second at 4 a second

            # while this address's next error is held back, it holds no place: with room for one
            # request in progress, a good pair from the same address is answered at once
            with ThreadPoolExecutor(1) as pool:
                held = pool.submit(client.post, "/disparity", files=missing_right)
                time.sleep(0.05)
                good = client.post("/disparity", files=pair_files(*stereo_pair()))
                assert held.result().status_code == 422
            assert good.status_code == 200, good.text
            assert client.get("/health/live").status_code == 200

        # another address has a budget of its own
        other = httpx.Client(
            base_url=server.base_url, timeout=30, transport=httpx.HTTPTransport(local_address="127.0.0.2")
        )
        with other:
            started = time.perf_counter()
            assert other.post("/disparity", files=missing_right).status_code == 422
            assert time.perf_counter() - started < 0.2
        delayed = metric_total(httpx.get(server.base_url + "/metrics").text, "crestereo_client_errors_delayed_total")
    assert delayed >= 5
