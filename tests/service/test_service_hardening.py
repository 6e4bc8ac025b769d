"""Attacks that once took the server down, each against a real uvicorn process on loopback."""

from __future__ import annotations

import os
import socket
import struct
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import httpx
import pytest

from service.images import ImageError, read_header
from service_helpers import REPO, encode, metric_total, run_uvicorn, stereo_pair


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


def test_a_tiff_with_repeated_size_tags_is_refused_from_its_header():
    with pytest.raises(ImageError, match="repeated width or height"):
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
    ] * 2
    with httpx.Client(base_url=default_server.base_url, timeout=60) as client, ThreadPoolExecutor(4) as pool:
        answers = pool.map(lambda files: client.post("/disparity", files=files), attacks)
        live_seconds = []
        for _ in range(20):
            started = time.perf_counter()
            assert client.get("/health/live").status_code == 200
            live_seconds.append(time.perf_counter() - started)
            time.sleep(0.05)
        answers = list(answers)
    assert [(a.status_code, a.json()["error"]["code"]) for a in answers] == [(422, "undecodable_image")] * 4
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


@pytest.mark.parametrize("size", [20_000, 1_000_000])
def test_oversized_request_headers_get_a_json_431_and_the_server_stays_up(default_server, size):
    response = httpx.post(default_server.base_url + "/disparity", headers={"X-Big": "a" * size})
    assert response.status_code == 431
    assert response.json()["error"]["code"] == "headers_too_large"
    assert httpx.get(default_server.base_url + "/health/live").status_code == 200


def test_idle_connections_beyond_the_concurrency_cap_get_503_not_a_hang(tmp_path):
    from service.__main__ import SERVER_LIMITS

    with run_uvicorn(tmp_path) as server:
        host, port = server.base_url.removeprefix("http://").split(":")
        idle = [socket.create_connection((host, int(port))) for _ in range(SERVER_LIMITS["limit_concurrency"])]
        try:
            time.sleep(0.2)
            capped = httpx.get(server.base_url + "/health/live", timeout=5)
        finally:
            for sock in idle:
                sock.close()
        time.sleep(0.2)
        after = httpx.get(server.base_url + "/health/live", timeout=5)
    assert capped.status_code == 503
    assert after.status_code == 200
