"""A client's jobs, picked at random by weight (JOBS), and the classification of every answer: `ok`
(200), `expected` (a JSON 4xx to a malformed job), `shed` (the service refusing work as it says it
will) or `unexpected` (anything else: the benchmark fails)."""

from __future__ import annotations

import json
import os
import random
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import httpx
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from .payloads import Pair, Payloads

FORMATS = ("json", "npz", "png", "disparity_png16", "uncertainty_png16", "ply")
STREAM_SHED_CODES = {"queue_full", "deadline_exceeded", "overloaded"}  # a stream's frame or close, not a failure
PAGE = 1 << 20


@dataclass
class Outcome:
    job: str
    status: str  # HTTP status, or `ws:<close code>`, `ws-frame`, `ws-closed`, `transport`
    code: str  # the JSON error code ("" for 200), or what went wrong
    verdict: str  # ok, expected, shed, unexpected
    seconds: float


def error_code(body: bytes) -> str | None:
    """The service's error code in a JSON error body (`{"error": {"code": ...}}`), else None."""
    try:
        return str(json.loads(body)["error"]["code"])
    except (ValueError, KeyError, TypeError):
        return None


def classify(job: str, response: httpx.Response, malformed: bool, seconds: float) -> Outcome:
    if response.status_code == 200:
        return Outcome(job, "200", "", "ok", seconds)
    code = error_code(response.content)
    if response.status_code == 503 and code is not None and "retry-after" in response.headers:
        verdict = "shed"
    elif malformed and code is not None and 400 <= response.status_code < 500:
        verdict = "expected"
    else:
        verdict = "unexpected"
    return Outcome(job, str(response.status_code), response.text[:60] if code is None else code, verdict, seconds)


def transport_error(job: str, error: Exception, started: float) -> Outcome:
    """No answer at all (a refused or dropped connection, a timeout): always unexpected."""
    return Outcome(job, "transport", type(error).__name__, "unexpected", time.perf_counter() - started)


class Client:
    """One client thread's job picker: a `random.Random` of its own, an HTTP client of its own."""

    def __init__(self, base_url: str, payloads: Payloads, seed: int, timeout_s: float) -> None:
        self.base_url = base_url
        self.payloads = payloads
        self.rng = random.Random(seed)
        self.http = httpx.Client(base_url=base_url, timeout=timeout_s)
        self.timeout_s = timeout_s

    def close(self) -> None:
        self.http.close()

    def post(
        self, job: str, pair: Pair, params: dict[str, Any], malformed: bool = False, deadline_ms: int | None = None
    ) -> list[Outcome]:
        headers = {} if deadline_ms is None else {"X-Request-Timeout-Ms": str(deadline_ms)}
        started = time.perf_counter()
        try:
            response = self.http.post("/disparity", params=params, files=pair.files(), headers=headers)
        except httpx.HTTPError as error:
            return [transport_error(job, error, started)]
        return [classify(job, response, malformed, time.perf_counter() - started)]

    def options(self) -> dict[str, Any]:
        rng = self.rng
        params: dict[str, Any] = {"format": rng.choice(FORMATS)}
        iters = rng.choice([None, None, None, "4", "2,2,3", "8"])
        if iters is not None:
            params["iters"] = iters
        scale = rng.choice([None, None, 0.5, 0.75])
        if scale is not None:
            params["scale"] = scale
        two_pass = rng.choice([None, None, "false", "true"])
        if two_pass is not None:
            params["two_pass"] = two_pass
        return params

    def deadline(self) -> int | None:
        return 4000 if self.rng.random() < 0.15 else None

    # each job returns the outcomes of its answers
    def dev_pair(self) -> list[Outcome]:
        pair = self.rng.choice(self.payloads.dev)
        return self.post("dev", pair, {"format": self.rng.choice(FORMATS)}, deadline_ms=self.deadline())

    def variant(self) -> list[Outcome]:
        return self.post(
            "variant", self.rng.choice(self.payloads.variants), self.options(), deadline_ms=self.deadline()
        )

    def full(self) -> list[Outcome]:
        return self.post("full", self.rng.choice(self.payloads.small), {"model": "full", "format": "npz"})

    def raw(self) -> list[Outcome]:
        params = {"format": self.rng.choice(["json", "npz", "depth_png16", "ply"])}
        if self.rng.random() < 0.3:
            params["frame"] = "original"
        return self.post("raw", self.rng.choice(self.payloads.raw), params, deadline_ms=self.deadline())

    def malformed(self) -> list[Outcome]:
        rng, p = self.rng, self.payloads
        kind = rng.choice(["undecodable", "calibration", "mismatch", "option"])
        if kind == "undecodable":
            good = rng.choice(p.dev)
            pair = Pair("undecodable", 0, 0, good.left, b"\x89PNG\r\n\x1a\n" + os.urandom(2048))
            return self.post("bad:undecodable", pair, {}, malformed=True)
        if kind == "calibration":
            return self.post("bad:calibration", p.bad_calibration, {}, malformed=True)
        if kind == "mismatch":
            return self.post("bad:mismatch", p.mismatch, {}, malformed=True)
        return self.post("bad:option", rng.choice(p.small), {"iters": "0,x"}, malformed=True)

    def stream(self) -> list[Outcome]:
        frames = self.payloads.stream_frames
        fmt = self.rng.choice(["npz", "json", "disparity_png16"])
        url = self.base_url.replace("http", "ws", 1) + f"/disparity/stream?format={fmt}&warm_iters=3"
        outcomes: list[Outcome] = []
        started = time.perf_counter()
        try:
            with connect(url, max_size=64 * PAGE, open_timeout=30) as socket:
                for pair in frames[: self.rng.randint(2, len(frames))]:
                    socket.send(pair.left)
                    socket.send(pair.right)
                    message = socket.recv(timeout=self.timeout_s)
                    elapsed = time.perf_counter() - started
                    started = time.perf_counter()
                    if isinstance(message, bytes) or "error" not in (said := json.loads(message)):
                        outcomes.append(Outcome("stream", "200", "", "ok", elapsed))
                        continue
                    code = said["error"]["code"]
                    verdict = "shed" if code in STREAM_SHED_CODES else "unexpected"
                    if "frame" in said:  # a frame that could not be computed: the stream goes on
                        outcomes.append(Outcome("stream", "ws-frame", code, verdict, elapsed))
                    else:  # why the server closes the stream (1013 `overloaded`: too many streams, say)
                        outcomes.append(Outcome("stream", "ws-closed", code, verdict, elapsed))
                        break
        except InvalidStatus as refused:  # refused at the handshake: shed where it is the JSON 503 with Retry-After
            answer = refused.response
            code = error_code(bytes(answer.body or b"")) or "not-json"
            shed = answer.status_code == 503 and code == "overloaded" and "Retry-After" in answer.headers
            verdict = "shed" if shed else "unexpected"
            outcomes.append(Outcome("stream", str(answer.status_code), code, verdict, time.perf_counter() - started))
        except ConnectionClosed as closed:
            code = closed.rcvd.code if closed.rcvd is not None else 1006
            reason = closed.rcvd.reason if closed.rcvd is not None else ""
            verdict = "shed" if code in {1013, 1001} else "unexpected"
            outcomes.append(Outcome("stream", f"ws:{code}", reason[:40], verdict, time.perf_counter() - started))
        except (OSError, TimeoutError) as error:
            outcomes.append(transport_error("stream", error, started))
        return outcomes


JOBS: dict[str, tuple[float, Callable[[Client], list[Outcome]]]] = {
    "dev": (0.20, Client.dev_pair),
    "variant": (0.36, Client.variant),
    "full": (0.04, Client.full),
    "raw": (0.16, Client.raw),
    "stream": (0.10, Client.stream),
    "malformed": (0.14, Client.malformed),
}
