"""`StereoClient` and `AsyncStereoClient`: one request builder and one response reader, two loops."""

from __future__ import annotations

import asyncio
import base64
import io
import json
import os
import time
from collections.abc import Sequence
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

Image = np.ndarray | bytes | str | os.PathLike[str]
"""An image: HxW or HxWx3 RGB array (uint8 or uint16), encoded file bytes, or a file path."""

CalibrationFile = bytes | str | os.PathLike[str]
"""A calibration file: its bytes, or its path."""

Calibration = CalibrationFile | Sequence[CalibrationFile]
"""One OpenCV calibration file (K1, D1, K2, D2, R, T and the image size), or two ROS camera_info
files (left, right)."""

RETRIED_CODES = frozenset({"queue_full", "loading"})
"""503 codes worth retrying after `Retry-After`; others (draining, deadline_exceeded, ...) are not."""


class ServiceError(Exception):
    """An error answer of the service: HTTP `status`, its stable `code` and `message`, and the
    `retry_after` seconds it suggested (None without the header)."""

    def __init__(self, status: int, code: str, message: str, retry_after: float | None = None) -> None:
        super().__init__(f"{status} {code}: {message}")
        self.status, self.code, self.message, self.retry_after = status, code, message, retry_after


@dataclass(frozen=True)
class DisparityResult:
    """The maps (float32 HxW: disparity in px of the left image, uncertainty, depth in m when
    a calibration or focal length and baseline were given) and the facts the service reports
    about the computation. A raw pair's maps are in the rectified left image, or with
    `frame="original"` in the original left image's pixels (+inf disparity and depth,
    uncertainty 1, where a pixel has no rectified counterpart)."""

    disparity: np.ndarray
    uncertainty: np.ndarray
    depth: np.ndarray | None
    model: str
    weights: str
    batch_size: int
    queue_ms: float
    compute_ms: float


@dataclass
class _Retries:
    """At most `max_retries` retries, waiting what the service asks, never above `max_wait_s`."""

    max_retries: int
    max_wait_s: float

    def wait_for(self, error: ServiceError, attempt: int) -> float | None:
        """Seconds to wait before retrying after `error` on `attempt` (0-based), or None."""
        if error.code not in RETRIED_CODES or attempt >= self.max_retries:
            return None
        return min(self.max_wait_s, error.retry_after if error.retry_after is not None else 1.0)


def _encode(image: Image) -> bytes:
    if isinstance(image, bytes):
        return image
    if isinstance(image, (str, os.PathLike)):
        return Path(image).read_bytes()
    array = np.asarray(image)
    if array.ndim == 3 and array.shape[2] == 3:
        array = np.ascontiguousarray(array[:, :, ::-1])  # RGB -> OpenCV's BGR
    elif array.ndim != 2:
        raise ValueError(f"expected an HxW or HxWx3 image, got shape {array.shape}")
    ok, encoded = cv2.imencode(".png", array)
    if not ok:
        raise ValueError("could not encode the image as PNG")
    return encoded.tobytes()


_UNSENT_DEFAULTS: dict[str, Any] = {"flip": False, "blend_sgbm": True, "refine_edges": True, "frame": "rectified"}
"""Options left out of the query at these values, the service's defaults: a service older than the
option then still answers a request that does not use it."""


def _query(response_format: str, options: dict[str, Any]) -> dict[str, str]:
    """The query string of a request: `format` and the options given (None, and the
    `_UNSENT_DEFAULTS`, left out: the service's default)."""
    given = {
        k: _query_value(v)
        for k, v in options.items()
        if v is not None and not (k in _UNSENT_DEFAULTS and v == _UNSENT_DEFAULTS[k])
    }
    return {"format": response_format, **given}


def _request(left: Image, right: Image, calibration: Calibration | None, options: dict[str, Any]) -> dict[str, Any]:
    params = _query("npz", options)
    files = [("left", ("left.png", _encode(left))), ("right", ("right.png", _encode(right)))]
    if calibration is not None:
        parts = [calibration] if isinstance(calibration, bytes | str | os.PathLike) else list(calibration)
        for part in parts:
            data = part if isinstance(part, bytes) else Path(part).read_bytes()
            files.append(("calibration", ("calibration.yaml", data)))
    return {"params": params, "files": files}


def _query_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (tuple, list)):
        return ",".join(str(v) for v in value)
    return str(value)


def _error(status: int, body: bytes, retry_after: str | None) -> ServiceError:
    """The error of an HTTP answer (a request's, or a stream's refused handshake): the service's
    JSON `{"error": {"code", "message"}}`, else (a proxy, uvicorn itself) `http_error` with the text."""
    try:
        error = json.loads(body)["error"]
        code, message = str(error["code"]), str(error["message"])
    except (ValueError, KeyError, TypeError):
        code, message = "http_error", body[:200].decode(errors="replace")
    return ServiceError(status, code, message, float(retry_after) if retry_after else None)


def _result(response: httpx.Response) -> DisparityResult:
    if response.status_code != 200:
        raise _error(response.status_code, response.content, response.headers.get("retry-after"))
    maps = np.load(io.BytesIO(response.content))
    headers = response.headers
    return DisparityResult(
        disparity=maps["disparity"],
        uncertainty=maps["uncertainty"],
        depth=maps["depth"] if "depth" in maps.files else None,
        model=headers["x-model"],
        weights=headers["x-weights"],
        batch_size=int(headers["x-batch-size"]),
        queue_ms=float(headers["x-queue-ms"]),
        compute_ms=float(headers["x-compute-ms"]),
    )


def _json(response: httpx.Response) -> Any:
    if response.status_code >= 400 and response.status_code != 503:
        raise _error(response.status_code, response.content, response.headers.get("retry-after"))
    return response.json()


class StereoClient:
    """Synchronous client. `max_retries`: retries of a request refused with 503 `queue_full` or
    `loading`, each after the `Retry-After` the service sent (capped at `max_retry_wait_s`)."""

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8000",
        *,
        api_key: str | None = None,
        timeout_s: float = 300.0,
        max_retries: int = 3,
        max_retry_wait_s: float = 30.0,
    ) -> None:
        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        self._http = httpx.Client(base_url=base_url, headers=headers, timeout=timeout_s)
        self._retries = _Retries(max_retries, max_retry_wait_s)

    def disparity(
        self,
        left: Image,
        right: Image,
        *,
        model: str = "lite",
        iters: int | tuple[int, int, int] | None = None,
        scale: float | None = None,
        two_pass: bool | str = "auto",
        raw_uncertainty: bool = False,
        flip: bool = False,
        blend_sgbm: bool = True,
        refine_edges: bool = True,
        focal_px: float | None = None,
        baseline_m: float | None = None,
        calibration: Calibration | None = None,
        frame: str = "rectified",
    ) -> DisparityResult:
        """Disparity and uncertainty of a rectified pair, or of a raw pair with its `calibration`
        (raises `ServiceError` on an error answer). `two_pass`: True, False or "auto" (a quick pass
        decides: two passes where it finds large disparities, one elsewhere, the pair enlarged up
        to 1.5x as far as their range allows, or shrunk where two passes could not hold it).
        `flip`: also compute the pair upside down and merge the two answers (about twice the time,
        fewer errors). `blend_sgbm`: the answer averaged with OpenCV's SGBM where the two agree
        within 4 px (fewer errors). `refine_edges`: the answer refined at its edges: its depth edges
        put where the left image's colour edges are, the strip along the image's left edge whose
        matches fall outside the right image raised (fewer errors at the edges of objects and of
        the image). Both False: the network's own answer."""
        request = _request(
            left,
            right,
            calibration,
            dict(
                model=model,
                iters=iters,
                scale=scale,
                two_pass=two_pass,
                raw_uncertainty=raw_uncertainty,
                flip=flip,
                blend_sgbm=blend_sgbm,
                refine_edges=refine_edges,
                focal_px=focal_px,
                baseline_m=baseline_m,
                frame=frame,
            ),
        )
        for attempt in range(self._retries.max_retries + 1):
            try:
                return _result(self._http.post("/disparity", **request))
            except ServiceError as error:
                wait = self._retries.wait_for(error, attempt)
                if wait is None:
                    raise
                time.sleep(wait)
        raise AssertionError("unreachable: the last attempt returns or raises")

    def stream(
        self,
        *,
        model: str = "lite",
        iters: int | tuple[int, int, int] | None = None,
        warm_iters: int | None = None,
        scale: float | None = None,
        raw_uncertainty: bool = False,
        flip: bool = False,
        blend_sgbm: bool = True,
        refine_edges: bool = True,
        focal_px: float | None = None,
        baseline_m: float | None = None,
    ) -> DisparityStream:
        """A WebSocket stream (`/disparity/stream`) for the rectified pairs of one camera, each
        frame warm-started from the previous one (`warm_iters` iterations; see `DisparityStream`)."""
        options = dict(
            model=model,
            iters=iters,
            warm_iters=warm_iters,
            scale=scale,
            raw_uncertainty=raw_uncertainty,
            flip=flip,
            blend_sgbm=blend_sgbm,
            refine_edges=refine_edges,
            focal_px=focal_px,
            baseline_m=baseline_m,
        )
        url = httpx.URL(str(self._http.base_url)).join("disparity/stream").copy_merge_params(_query("json", options))
        ws_url = str(url).replace("http://", "ws://", 1).replace("https://", "wss://", 1)
        return DisparityStream(ws_url, self._http.headers.get("Authorization"), self._http.timeout.read)

    def health(self) -> dict[str, Any]:
        """`GET /health` (also when the service answers 503: the body says why)."""
        return dict(_json(self._http.get("/health")))

    def models(self) -> list[dict[str, Any]]:
        """`GET /models`: what each loaded model is."""
        return list(_json(self._http.get("/models"))["models"])

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> StereoClient:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


class DisparityStream:
    """One WebSocket connection to `/disparity/stream`: `send(left, right)` sends the next pair
    and returns its maps (a `DisparityResult`), or raises `ServiceError` for a frame the service
    could not compute (the stream stays open); closing the stream closes the connection."""

    def __init__(self, url: str, authorization: str | None, timeout_s: float | None) -> None:
        headers = {"Authorization": authorization} if authorization else None
        self._connection = ExitStack()
        try:
            self._socket = self._connection.enter_context(
                connect(url, additional_headers=headers, max_size=None, open_timeout=timeout_s)
            )
        except InvalidStatus as refused:  # a key or a place refused at the handshake, in the service's JSON
            answer = refused.response
            raise _error(answer.status_code, bytes(answer.body or b""), answer.headers.get("Retry-After")) from None
        self._timeout_s = timeout_s

    def send(self, left: Image, right: Image) -> DisparityResult:
        self._socket.send(_encode(left))
        self._socket.send(_encode(right))
        try:
            message = self._socket.recv(timeout=self._timeout_s)
        except ConnectionClosed as closed:
            reason = closed.rcvd.reason if closed.rcvd else "connection closed"
            raise ServiceError(0, "stream_closed", reason) from None
        body = json.loads(message)
        if "error" in body:
            raise ServiceError(0, str(body["error"]["code"]), str(body["error"]["message"]))
        return _json_result(body)

    def close(self) -> None:
        self._connection.close()

    def __enter__(self) -> DisparityStream:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


def _json_result(body: dict[str, Any]) -> DisparityResult:
    """The result of a `format=json` answer."""

    def array(encoded: dict[str, Any]) -> np.ndarray:
        return np.frombuffer(base64.b64decode(encoded["data"]), "<f4").reshape(encoded["shape"])

    timings = body["timings"]
    return DisparityResult(
        disparity=array(body["disparity"]),
        uncertainty=array(body["uncertainty"]),
        depth=array(body["depth"]) if body.get("depth") else None,
        model=body["model"],
        weights=body["weights"],
        batch_size=int(body["batch_size"]),
        queue_ms=float(timings["queue_ms"]),
        compute_ms=float(timings["compute_ms"]),
    )


class AsyncStereoClient:
    """`StereoClient` for asyncio: the same methods, awaited."""

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8000",
        *,
        api_key: str | None = None,
        timeout_s: float = 300.0,
        max_retries: int = 3,
        max_retry_wait_s: float = 30.0,
    ) -> None:
        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        self._http = httpx.AsyncClient(base_url=base_url, headers=headers, timeout=timeout_s)
        self._retries = _Retries(max_retries, max_retry_wait_s)

    async def disparity(
        self,
        left: Image,
        right: Image,
        *,
        model: str = "lite",
        iters: int | tuple[int, int, int] | None = None,
        scale: float | None = None,
        two_pass: bool | str = "auto",
        raw_uncertainty: bool = False,
        flip: bool = False,
        blend_sgbm: bool = True,
        refine_edges: bool = True,
        focal_px: float | None = None,
        baseline_m: float | None = None,
        calibration: Calibration | None = None,
        frame: str = "rectified",
    ) -> DisparityResult:
        request = _request(
            left,
            right,
            calibration,
            dict(
                model=model,
                iters=iters,
                scale=scale,
                two_pass=two_pass,
                raw_uncertainty=raw_uncertainty,
                flip=flip,
                blend_sgbm=blend_sgbm,
                refine_edges=refine_edges,
                focal_px=focal_px,
                baseline_m=baseline_m,
                frame=frame,
            ),
        )
        for attempt in range(self._retries.max_retries + 1):
            try:
                return _result(await self._http.post("/disparity", **request))
            except ServiceError as error:
                wait = self._retries.wait_for(error, attempt)
                if wait is None:
                    raise
                await asyncio.sleep(wait)
        raise AssertionError("unreachable: the last attempt returns or raises")

    async def health(self) -> dict[str, Any]:
        return dict(_json(await self._http.get("/health")))

    async def models(self) -> list[dict[str, Any]]:
        return list(_json(await self._http.get("/models"))["models"])

    async def close(self) -> None:
        await self._http.aclose()

    async def __aenter__(self) -> AsyncStereoClient:
        return self

    async def __aexit__(self, *_: object) -> None:
        await self.close()
