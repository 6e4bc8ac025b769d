"""`crestereo-pp serve --ray`: the service as a Ray Serve application on a real local Ray cluster
(two replicas of one CPU each, lite on torch), reached over HTTP through Ray's proxy."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
from ray_helpers import CROP_HEIGHT, CROP_WIDTH, ray_processes, real_crops, replica_processes

from crestereo_pp.service.local import REPO, LocalService, free_port, start_service
from service_helpers import assert_same_maps, decode_array, quiet_load_model

pytest.importorskip("ray", reason="the `ray` extra is not installed")

READY_TIMEOUT_S = 300  # a cluster, two replicas and their models, on a busy 2-core machine


def png(image: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".png", image)
    assert ok
    return data.tobytes()


@pytest.fixture(scope="module")
def ray_service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[LocalService, Path]]:
    """`crestereo-pp serve --ray --replicas 2 --replica-cpus 1` on a free port, once both replicas
    run (the command says so once Ray Serve has deployed them all) and the proxy routes to both."""
    log_path = tmp_path_factory.mktemp("ray-serve") / "serve.log"
    settings = {"CRESTEREO_MODELS": "lite", "CRESTEREO_BACKEND": "torch", "PYTHONWARNINGS": "ignore::RuntimeWarning"}
    command = ("-m", "crestereo_pp.cli.main", "serve", "--ray", "--replicas", "2", "--replica-cpus", "1")
    with log_path.open("wb") as log:
        try:
            service = start_service(settings, log, READY_TIMEOUT_S, command)
        except RuntimeError as error:
            raise AssertionError(f"{error}:\n{log_path.read_text(errors='replace')}") from None
    deadline = time.monotonic() + READY_TIMEOUT_S
    while "serving on" not in log_path.read_text(errors="replace"):
        assert time.monotonic() < deadline, log_path.read_text(errors="replace")
        time.sleep(0.5)
    seen: set[str] = set()
    while len(seen) < 2:
        assert time.monotonic() < deadline, f"the proxy routed only to {seen}"
        seen.add(httpx.get(f"{service.base_url}/health/live").headers["x-replica"])
    try:
        yield service, log_path
    finally:
        service.stop(timeout_s=90)


def test_sigterm_while_the_replicas_wait_for_cpus_stops_at_once_and_leaves_nothing_running(tmp_path: Path):
    before = set(ray_processes())
    log_path = tmp_path / "serve.log"
    command = ["-m", "crestereo_pp.cli.main", "serve", "--ray", "--replica-cpus", "100000", "--port", str(free_port())]
    with log_path.open("wb") as log:
        process = subprocess.Popen([sys.executable, *command], cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + READY_TIMEOUT_S
        while "starting replicas of 100000 CPU(s) each" not in log_path.read_text(errors="replace"):
            assert process.poll() is None and time.monotonic() < deadline, log_path.read_text(errors="replace")
            time.sleep(0.5)
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=30) == 0, log_path.read_text(errors="replace")
    finally:
        process.kill()
    deadline = time.monotonic() + 30
    while set(ray_processes()) - before:
        assert time.monotonic() < deadline, f"still running: {set(ray_processes()) - before}"
        time.sleep(0.5)


def post_pair(base_url: str, left: np.ndarray, right: np.ndarray) -> httpx.Response:
    files = {"left": ("left.png", png(left)), "right": ("right.png", png(right))}
    return httpx.post(f"{base_url}/disparity", params={"model": "lite"}, files=files, timeout=300)


def test_sixteen_concurrent_requests_are_all_answered_by_both_replicas_with_the_maps_of_the_model(ray_service):
    service, _ = ray_service
    crops = real_crops(4)
    with ThreadPoolExecutor(16) as pool:
        answers = list(pool.map(lambda i: post_pair(service.base_url, *crops[i % 4]), range(16)))
    assert [answer.status_code for answer in answers] == [200] * 16, [answer.text[:200] for answer in answers]
    assert len({answer.headers["x-replica"] for answer in answers}) == 2
    predictor = quiet_load_model("lite", backend="torch")
    for index, answer in enumerate(answers[:4]):
        left, right = (cv2.cvtColor(image, cv2.COLOR_BGR2RGB) for image in crops[index])
        disparity = decode_array(answer.json()["disparity"])
        assert disparity.shape == (CROP_HEIGHT, CROP_WIDTH)
        assert_same_maps(disparity, predictor.predict(left, right).disparity)


def test_behind_ray_the_routes_errors_and_page_are_the_services_and_threads_are_the_cpu_share(ray_service):
    service, _ = ray_service
    health = httpx.get(f"{service.base_url}/health").json()
    assert health["status"] == "ready" and health["models"]["lite"]["loaded"]
    assert health["batching"]["torch_threads"] == 1  # --replica-cpus 1
    assert [model["name"] for model in httpx.get(f"{service.base_url}/models").json()["models"]] == ["lite"]
    page = httpx.get(f"{service.base_url}/")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    left, _ = real_crops(1)[0]
    missing_right = httpx.post(f"{service.base_url}/disparity", files={"left": ("left.png", png(left))})
    assert missing_right.status_code == 422
    assert missing_right.json()["error"]["code"]
    assert missing_right.headers["x-replica"]
    assert missing_right.headers.get_list("x-request-id") == [missing_right.headers["x-request-id"]]


def cpu_seconds(pid: int) -> float:
    """User and system CPU time of process `pid` so far (from /proc/PID/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def wait_until_computing(pid: int, timeout_s: float = 60.0) -> None:
    """Return once process `pid` uses at least a third of a CPU over 0.3 s (a replica computing a
    batch; an idle one uses about 1 %)."""
    deadline = time.monotonic() + timeout_s
    while True:
        before = cpu_seconds(pid)
        time.sleep(0.3)
        if cpu_seconds(pid) - before >= 0.1:
            return
        assert time.monotonic() < deadline, f"replica {pid} never started computing"


def post_until(
    stop: threading.Event, base_url: str, crops: list[tuple[np.ndarray, np.ndarray]], first: int, step: int
) -> list[tuple[int, httpx.Response]]:
    """Post crops[first], crops[first + step], ... (cycling) until `stop` is set; the (crop index,
    answer) of each request, the one in flight when `stop` is set included."""
    answers: list[tuple[int, httpx.Response]] = []
    index = first
    while not stop.is_set():
        answers.append((index % len(crops), post_pair(base_url, *crops[index % len(crops)])))
        index += step
    return answers


def test_a_replica_killed_under_load_answers_each_request_with_its_maps_or_refuses_it_503_and_is_replaced(
    ray_service,
):
    service, _ = ray_service
    crops = real_crops(4)
    for _ in range(KILL_TRIES):  # a replica seen computing may have just finished its last batch
        victim, indexed = kill_under_load(service.base_url, crops)
        answers = [answer for _, answer in indexed]
        lost = [answer for answer in answers if answer.status_code != 200]
        if lost:
            break
        wait_until_replaced(victim)
    assert lost, f"no request was in flight on the killed replica, {KILL_TRIES} times"
    assert any(answer.status_code == 200 for answer in answers), "the other replica answered nothing"
    predictor = quiet_load_model("lite", backend="torch")
    expected = [predictor.predict(*(cv2.cvtColor(image, cv2.COLOR_BGR2RGB) for image in crop)) for crop in crops]
    for index, answer in indexed:
        if answer.status_code == 200:  # an answer that came back is the pair's own, whichever replica gave it
            assert_same_maps(decode_array(answer.json()["disparity"]), expected[index].disparity)
        else:
            assert answer.status_code == 503, answer.text
            assert answer.headers["retry-after"] == "1"
            assert json.loads(answer.text)["error"]["code"] == "replica_lost"
    wait_until_replaced(victim)
    assert post_pair(service.base_url, *crops[0]).status_code == 200


KILL_TRIES = 3


def kill_under_load(
    base_url: str, crops: list[tuple[np.ndarray, np.ndarray]], clients: int = 8
) -> tuple[int, list[tuple[int, httpx.Response]]]:
    """Kill a replica while `clients` threads post `crops`: once it is seen computing, so that
    requests are in flight on it when it dies. The replica's pid, and every (crop index, answer)."""
    victim = replica_processes()[0]
    stop = threading.Event()
    with ThreadPoolExecutor(clients) as pool:  # a load that lasts until the victim is seen computing
        pending = [pool.submit(post_until, stop, base_url, crops, i, clients) for i in range(clients)]
        try:
            wait_until_computing(victim)
            os.kill(victim, signal.SIGKILL)
        finally:
            stop.set()
        return victim, [answer for future in pending for answer in future.result()]


def wait_until_replaced(victim: int) -> None:
    """Return once two replicas run again, the killed `victim` not among them."""
    deadline = time.monotonic() + READY_TIMEOUT_S
    while not (len(replica_processes()) == 2 and victim not in replica_processes()):
        assert time.monotonic() < deadline, "the killed replica was not replaced"
        time.sleep(1)


def test_sigterm_stops_the_application_and_the_local_cluster_it_started(ray_service):
    service, log_path = ray_service
    assert ray_processes()
    service.process.send_signal(signal.SIGTERM)
    assert service.process.wait(timeout=120) == 0, log_path.read_text(errors="replace")
    deadline = time.monotonic() + 30
    while ray_processes():
        assert time.monotonic() < deadline, f"still running: {ray_processes()}"
        time.sleep(0.5)
