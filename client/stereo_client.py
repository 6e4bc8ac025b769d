"""`StereoClient` and `AsyncStereoClient`: one request builder and one reader per answer, two loops."""

from __future__ import annotations

import asyncio
import io
import json
import os
import time
from collections.abc import Callable, Mapping, Sequence
from contextlib import ExitStack
from dataclasses import dataclass
from itertools import count
from pathlib import Path
from typing import Any, Literal, TypedDict, TypeVar, Unpack
from urllib.parse import urlsplit

import cv2
import httpx
import numpy as np
from websockets.asyncio.client import ClientConnection
from websockets.asyncio.client import connect as connect_async
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import ClientConnection as ClientConnectionSync
from websockets.sync.client import connect

from crestereo_pp.stereo_data.formats import check_pixel_values
from crestereo_pp.stereo_data.pointcloud import METRIC_FRAME, decode_ply

Image = np.ndarray | bytes | str | os.PathLike[str]
"""An image: an array as `load_model(...).predict` takes it (HxW or HxWx1 grey, HxWx3 RGB, HxWx4
RGBA with the alpha dropped; uint8 and uint16 as they are, other numbers taken as 0-255), encoded
file bytes, or a file path."""

CalibrationFile = bytes | str | os.PathLike[str]
"""A calibration file: its bytes, or its path."""

Calibration = CalibrationFile | Sequence[CalibrationFile]
"""One OpenCV calibration file (K1, D1, K2, D2, R, T and the image size), or two ROS camera_info
files (left, right)."""

RETRIED_CODES = frozenset({"queue_full", "loading"})
"""503 codes worth retrying after `Retry-After`; others (draining, deadline_exceeded, ...) are not."""


class Options(TypedDict, total=False):
    """How the service computes a pair: the options of `disparity`, `point_cloud` and `stream`, as
    keywords. One left out takes the service's default (in brackets; the service's README has each
    in full).

    model: "lite" or "full" ["lite"]. iters: iterations at 1/4 resolution, or (1/16, 1/8, 1/4)
    [the model's]. scale: in (0, 1], the pair resized by it (faster, coarser) [1]. two_pass: True,
    False or "auto" (a quick pass decides: two passes where it finds large disparities, one
    elsewhere, the pair enlarged up to 1.5x as far as their range allows, or shrunk where two
    passes could not hold it) ["auto"]. raw_uncertainty: the paper's U instead of P(error > 2 px)
    [False]. flip: also compute the pair upside down and merge the two answers (about twice the
    time, fewer errors) [False]. blend_sgbm: the answer averaged with OpenCV's SGBM where the two
    agree within 4 px (fewer errors) [True]. refine_edges: depth edges put where the left image's
    colour edges are, and the strip along the image's left edge raised [True]; both False: the
    network's answer. align_rows: where the right image's rows are off the left's by a quarter
    pixel or more (measured on the pair), resample it onto them first [True]. focal_px,
    baseline_m: a rectified pair's camera (both or neither), for metric depth. min_disparity: no
    depth nor point at or below it (px) [1]. max_depth_m: none deeper (metres) [no limit].
    """

    model: Literal["lite", "full"]
    iters: int | tuple[int, int, int]
    scale: float
    two_pass: bool | Literal["auto"]
    raw_uncertainty: bool
    flip: bool
    blend_sgbm: bool
    refine_edges: bool
    align_rows: bool
    focal_px: float
    baseline_m: float
    min_disparity: float
    max_depth_m: float


class ServiceError(Exception):
    """An error answer of the service: HTTP `status`, its stable `code` and `message`, and the
    `retry_after` seconds it suggested (None without the header)."""

    def __init__(self, status: int, code: str, message: str, retry_after: float | None = None) -> None:
        super().__init__(f"{status} {code}: {message}")
        self.status, self.code, self.message, self.retry_after = status, code, message, retry_after


@dataclass(frozen=True)
class Camera:
    """The rectified left camera of a raw pair, which its disparity and depth refer to: depth =
    focal_px x baseline_m / disparity; pixel (x, y) looks along ((x - cx_px) / focal_px,
    (y - cy_px) / focal_px, 1)."""

    focal_px: float
    baseline_m: float
    cx_px: float
    cy_px: float


@dataclass(frozen=True)
class RowOffset:
    """How far the right image's rows lay off the left's, as the service measured them before
    matching: a left pixel's match lay dy px lower in the right image (negative: higher), dy(x, y)
    = centre_px + across_px * (x / W - 1/2) + down_px * (y / H - 1/2); largest_px the largest |dy|
    over the image, tracks the corners it was fitted to, aligned whether the service resampled
    the right image onto the left's rows (0.25 px or more somewhere). A pixel or more says that
    the rig's calibration is off."""

    centre_px: float
    across_px: float
    down_px: float
    largest_px: float
    tracks: int
    aligned: bool


@dataclass(frozen=True)
class Computation:
    """What the service says of a computation: the model, whether its weights are trained (False:
    its maps are not usable), the weights' identity (first 16 hex digits of their sha256), how many
    requests ran in its batch, its time queued and the batch's network time, a raw pair's
    rectified left camera (None for a rectified pair), and the right image's row offset as
    measured (None with `align_rows=False`, or where the pair had too little texture to measure)."""

    model: str
    trained: bool
    weights: str
    batch_size: int
    queue_ms: float
    compute_ms: float
    camera: Camera | None
    row_offset: RowOffset | None


@dataclass(frozen=True)
class DisparityResult(Computation):
    """The maps (float32 HxW: disparity in px of the left image, uncertainty, depth in m when
    a calibration or focal length and baseline were given). A raw pair's maps are in the rectified
    left image, or with `frame="original"` in the original left image's pixels (+inf disparity
    and depth, uncertainty 1, where a pixel has no rectified counterpart)."""

    disparity: np.ndarray
    uncertainty: np.ndarray
    depth: np.ndarray | None


@dataclass(frozen=True)
class PointCloud(Computation):
    """The pair's points, one per kept pixel in row-major order: `points` float32 Nx3, metres in the
    (rectified) left camera's frame (x right, y down, z forward) where `metric`, else image-space
    (column px, row px, disparity px); `colors` uint8 Nx3 RGB of the left image; `ply` the binary
    PLY file as the service sent it (write it to a `.ply` file as it is)."""

    points: np.ndarray
    colors: np.ndarray
    metric: bool
    ply: bytes


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
    """The image as the file that is sent: bytes and files as they are, an array as a PNG (uint8
    and uint16 as they are; other numbers, taken as 0-255, as a 16-bit PNG of 257 x the value)."""
    if isinstance(image, bytes):
        return image
    if isinstance(image, (str, os.PathLike)):
        return Path(image).read_bytes()
    array = np.asarray(image)
    if array.ndim == 3 and array.shape[2] in (1, 3, 4):
        array = array[:, :, 0] if array.shape[2] == 1 else np.ascontiguousarray(array[:, :, 2::-1])  # RGB -> BGR
    elif array.ndim != 2:
        raise ValueError(f"expected an HxW, HxWx1, HxWx3 or HxWx4 image, got shape {array.shape}")
    if array.dtype not in (np.uint8, np.uint16):
        check_pixel_values(array)
        array = np.round(array.astype(np.float64) * 257).astype(np.uint16)
    ok, encoded = cv2.imencode(".png", array)
    if not ok:
        raise ValueError("could not encode the image as PNG")
    return encoded.tobytes()


def _query(response_format: str, options: Mapping[str, Any], **extra: Any) -> dict[str, str]:
    """The query string of a request: `format`, the `options` a caller gave (TypeError for a keyword
    that is no `Options` key: a typo would otherwise reach the service) and the method's own
    `extra` ones; None left out (the service's default)."""
    unknown = sorted(set(options) - Options.__optional_keys__)
    if unknown:
        raise TypeError(f"unknown option {unknown[0]!r}; the options are {', '.join(Options.__annotations__)}")
    given = {**options, **extra}
    return {"format": response_format, **{k: _query_value(v) for k, v in given.items() if v is not None}}


def _query_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (tuple, list)):
        return ",".join(str(v) for v in value)
    return str(value)


def _request(
    response_format: str,
    left: Image,
    right: Image,
    calibration: Calibration | None,
    deadline_ms: int | None,
    options: Mapping[str, Any],
    **extra: Any,
) -> dict[str, Any]:
    """The keywords of `httpx.post` for one pair (`POST /disparity`); `options` and `extra` as `_query`."""
    files = [("left", ("left.png", _encode(left))), ("right", ("right.png", _encode(right)))]
    if calibration is not None:
        parts = [calibration] if isinstance(calibration, bytes | str | os.PathLike) else list(calibration)
        for part in parts:
            data = part if isinstance(part, bytes) else Path(part).read_bytes()
            files.append(("calibration", ("calibration.yaml", data)))
    headers = {} if deadline_ms is None else {"X-Request-Timeout-Ms": str(deadline_ms)}
    return {"params": _query(response_format, options, **extra), "files": files, "headers": headers}


def _error(status: int, body: bytes, retry_after: str | None) -> ServiceError:
    """The error of an HTTP answer (a request's, or a stream's refused handshake): the service's
    JSON `{"error": {"code", "message"}}`, else (a proxy, uvicorn itself) `http_error` with the text."""
    try:
        error = json.loads(body)["error"]
        code, message = str(error["code"]), str(error["message"])
    except (ValueError, KeyError, TypeError):
        code, message = "http_error", body[:200].decode(errors="replace")
    return ServiceError(status, code, message, float(retry_after) if retry_after else None)


ANSWER_MEDIA_TYPES = ("application/x-npz", "application/x-ply")
"""The media types of the answers the client asks `POST /disparity` for."""


def _not_a_service(response: httpx.Response, wanted: str) -> ServiceError:
    """The error for an answer that no crestereo-pp service gives (another server at the address)."""
    media_type = response.headers.get("content-type") or "no content type"
    return ServiceError(
        response.status_code,
        "not_a_service",
        f"{response.request.url} answered {media_type} where the service answers {wanted}: "
        "is this the address of a crestereo-pp service?",
    )


def _answered(response: httpx.Response) -> bytes:
    """The body of a 200 answer (ServiceError for an error answer, or one no service gives)."""
    if response.status_code != 200:
        raise _error(response.status_code, response.content, response.headers.get("retry-after"))
    if response.headers.get("content-type", "").split(";")[0].strip() not in ANSWER_MEDIA_TYPES:
        raise _not_a_service(response, " or ".join(ANSWER_MEDIA_TYPES))
    return response.content


def _computation(facts: str) -> dict[str, Any]:
    """The `Computation` fields of an answer's facts: the JSON every binary answer carries inside
    its file (an npz's `facts` array, a PLY's `comment facts` line)."""
    body = json.loads(facts)
    timings = body["timings"]
    return dict(
        model=body["model"],
        trained=body["model_status"] == "trained",
        weights=body["weights"],
        batch_size=int(body["batch_size"]),
        queue_ms=float(timings["queue_ms"]),
        compute_ms=float(timings["compute_ms"]),
        camera=Camera(**body["camera"]) if body.get("camera") else None,
        row_offset=RowOffset(**body["row_offset"]) if body.get("row_offset") else None,
    )


def _disparity_result(npz: bytes) -> DisparityResult:
    """The result of a `format=npz` answer (a request's body, or a stream's binary message)."""
    maps = np.load(io.BytesIO(npz))
    depth = maps["depth"] if "depth" in maps.files else None
    return DisparityResult(
        **_computation(maps["facts"].item()), disparity=maps["disparity"], uncertainty=maps["uncertainty"], depth=depth
    )


def _point_cloud(ply: bytes) -> PointCloud:
    """The result of a `format=ply` answer."""
    points, colors, frame, comments = decode_ply(ply)
    facts = next(comment.removeprefix("facts ") for comment in comments if comment.startswith("facts "))
    return PointCloud(**_computation(facts), points=points, colors=colors, metric=frame == METRIC_FRAME, ply=ply)


def _json(response: httpx.Response) -> Any:
    if response.status_code >= 400 and response.status_code != 503:
        raise _error(response.status_code, response.content, response.headers.get("retry-after"))
    try:
        return response.json()
    except ValueError:
        raise _not_a_service(response, "JSON") from None


Result = TypeVar("Result")


def service_address(url: str) -> str:
    """`url` as the address of a service (``http://host:port``, ``https://...``); a ValueError
    naming the form where it has no such scheme or no host (``localhost:8000``)."""
    address = urlsplit(url)
    if address.scheme not in ("http", "https") or not address.netloc:
        example = f" (for example http://{url})" if "://" not in url else ""
        raise ValueError(f"{url}: the service's address starts with http:// or https://{example}")
    return url


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
        self._http = httpx.Client(base_url=service_address(base_url), headers=headers, timeout=timeout_s)
        self._retries = _Retries(max_retries, max_retry_wait_s)

    def disparity(
        self,
        left: Image,
        right: Image,
        *,
        calibration: Calibration | None = None,
        frame: Literal["rectified", "original"] | None = None,
        deadline_ms: int | None = None,
        **options: Unpack[Options],
    ) -> DisparityResult:
        """Disparity and uncertainty of a rectified pair, or of a raw pair with its `calibration`
        (the maps in the rectified left image, or with `frame="original"` in the original one's
        pixels). `deadline_ms`: the service drops the request, answering 503 `deadline_exceeded`,
        where it cannot answer within this many milliseconds of its arrival. `options`: how to
        compute it (`Options`). Raises `ServiceError` on an error answer."""
        request = _request("npz", left, right, calibration, deadline_ms, options, frame=frame)
        return self._post(request, _disparity_result)

    def point_cloud(
        self,
        left: Image,
        right: Image,
        *,
        calibration: Calibration | None = None,
        max_uncertainty: float | None = None,
        cx_px: float | None = None,
        cy_px: float | None = None,
        deadline_ms: int | None = None,
        **options: Unpack[Options],
    ) -> PointCloud:
        """The pair's point cloud, coloured by the left image: metric with a `calibration` (raw
        pair) or `focal_px` and `baseline_m` (principal point `cx_px`, `cy_px`, default the image
        centre), else image-space; pixels whose uncertainty is above `max_uncertainty` left out.
        The rest as `disparity`."""
        request = _request(
            "ply",
            left,
            right,
            calibration,
            deadline_ms,
            options,
            max_uncertainty=max_uncertainty,
            cx_px=cx_px,
            cy_px=cy_px,
        )
        return self._post(request, _point_cloud)

    def stream(
        self, *, warm_iters: int | tuple[int, int, int] | None = None, **options: Unpack[Options]
    ) -> DisparityStream:
        """A WebSocket stream (`/disparity/stream`) for the rectified pairs of one camera, each
        frame warm-started from the previous one (`warm_iters` iterations; see `DisparityStream`)."""
        url = _stream_url(self._http, _query("npz", options, warm_iters=warm_iters))
        return DisparityStream(url, self._http.headers.get("Authorization"), self._http.timeout.read)

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

    def _post(self, request: dict[str, Any], read: Callable[[bytes], Result]) -> Result:
        """`POST /disparity`, its answer's body read by `read`, retried as `_Retries` says."""
        for attempt in count():
            try:
                return read(_answered(self._http.post("/disparity", **request)))
            except ServiceError as error:
                wait = self._retries.wait_for(error, attempt)
                if wait is None:
                    raise
                time.sleep(wait)
        raise AssertionError("unreachable: the attempts never end")


def _stream_url(http: httpx.Client | httpx.AsyncClient, query: dict[str, str]) -> str:
    """The WebSocket URL of `/disparity/stream` on `http`'s service, with `query`."""
    url = httpx.URL(str(http.base_url)).join("disparity/stream").copy_merge_params(query)
    return str(url).replace("http://", "ws://", 1).replace("https://", "wss://", 1)


def _refused(refused: InvalidStatus) -> ServiceError:
    """A stream's handshake refused (a key, a place), in the service's JSON."""
    answer = refused.response
    return _error(answer.status_code, bytes(answer.body or b""), answer.headers.get("Retry-After"))


IDLE_CLOSE = 1000
"""The close code of a stream the service ended because no frame came for its idle timeout."""


def _ended(closed: ConnectionClosed, last: str | bytes | None) -> ServiceError | None:
    """Why the service ended a stream: ServiceError from its last message (`last`, the error it
    sent before closing) or else from the close's reason; None for a stream closed only for being
    idle, which `send` opens again."""
    if last is not None:
        try:
            _frame_result(last)
        except ServiceError as error:
            return error
    code, reason = (closed.rcvd.code, closed.rcvd.reason) if closed.rcvd else (None, "connection closed")
    if code == IDLE_CLOSE:
        return None
    return ServiceError(0, "stream_closed", reason or f"the service closed the stream (code {code})")


def _frame_result(message: str | bytes) -> DisparityResult:
    """A stream's answer to one pair: its maps (a binary npz message), or ServiceError for a pair
    it could not compute (a text message, the service's JSON error)."""
    if isinstance(message, bytes):
        return _disparity_result(message)
    error = json.loads(message)["error"]
    raise ServiceError(0, str(error["code"]), str(error["message"]))


class DisparityStream:
    """One WebSocket connection to `/disparity/stream`: `send(left, right)` sends the next pair
    and returns its maps (a `DisparityResult`), or raises `ServiceError` for a frame the service
    could not compute (the stream stays open) or for a stream it ended (bad options, a draining
    server); a stream the service closed for being idle is opened again by the next `send`, whose
    pair is then computed cold. Closing the stream closes the connection."""

    def __init__(self, url: str, authorization: str | None, timeout_s: float | None) -> None:
        self._url, self._timeout_s = url, timeout_s
        self._headers = {"Authorization": authorization} if authorization else None
        self._connection = ExitStack()
        self._socket = self._open()

    def _open(self) -> ClientConnectionSync:
        try:
            return self._connection.enter_context(
                connect(self._url, additional_headers=self._headers, max_size=None, open_timeout=self._timeout_s)
            )
        except InvalidStatus as refused:
            raise _refused(refused) from None

    def send(self, left: Image, right: Image) -> DisparityResult:
        pair = (_encode(left), _encode(right))
        for attempt in range(2):
            if attempt:  # the service closed the stream for being idle: a new one
                self._connection.close()
                self._socket = self._open()
            try:
                for image in pair:
                    self._socket.send(image)
                return _frame_result(self._socket.recv(timeout=self._timeout_s))
            except ConnectionClosed as closed:
                error = _ended(closed, self._last_message())
            if error is not None:
                raise error
        raise ServiceError(0, "stream_closed", "the service closed a new stream as idle before its first pair")

    def _last_message(self) -> str | bytes | None:
        """The message the service sent before closing, if any."""
        try:
            return self._socket.recv(timeout=0)
        except (ConnectionClosed, TimeoutError):
            return None

    def close(self) -> None:
        self._connection.close()

    def __enter__(self) -> DisparityStream:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


class AsyncDisparityStream:
    """`DisparityStream` for asyncio: `async with service.stream(...) as stream` opens the
    connection, `await stream.send(left, right)` computes each next pair."""

    def __init__(self, url: str, authorization: str | None, timeout_s: float | None) -> None:
        self._url, self._timeout_s = url, timeout_s
        self._headers = {"Authorization": authorization} if authorization else None
        self._socket: ClientConnection | None = None

    async def open(self) -> None:
        """Connect (ServiceError where the service refuses the stream)."""
        try:
            self._socket = await connect_async(
                self._url, additional_headers=self._headers, max_size=None, open_timeout=self._timeout_s
            )
        except InvalidStatus as refused:
            raise _refused(refused) from None

    async def send(self, left: Image, right: Image) -> DisparityResult:
        if self._socket is None:
            raise RuntimeError("the stream is not open: use `async with service.stream(...) as stream`")
        pair = (_encode(left), _encode(right))
        for attempt in range(2):
            if attempt:  # the service closed the stream for being idle: a new one
                await self.close()
                await self.open()
            assert self._socket is not None
            try:
                for image in pair:
                    await self._socket.send(image)
                return _frame_result(await asyncio.wait_for(self._socket.recv(), self._timeout_s))
            except ConnectionClosed as closed:
                error = _ended(closed, await self._last_message())
            if error is not None:
                raise error
        raise ServiceError(0, "stream_closed", "the service closed a new stream as idle before its first pair")

    async def _last_message(self) -> str | bytes | None:
        """The message the service sent before closing, if any."""
        assert self._socket is not None
        try:
            return await asyncio.wait_for(self._socket.recv(), 0.001)
        except (ConnectionClosed, TimeoutError):
            return None

    async def close(self) -> None:
        if self._socket is not None:
            await self._socket.close()

    async def __aenter__(self) -> AsyncDisparityStream:
        await self.open()
        return self

    async def __aexit__(self, *_: object) -> None:
        await self.close()


class AsyncStereoClient:
    """`StereoClient` for asyncio: the same methods, awaited (`stream` with `async with`)."""

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
        self._http = httpx.AsyncClient(base_url=service_address(base_url), headers=headers, timeout=timeout_s)
        self._retries = _Retries(max_retries, max_retry_wait_s)

    async def disparity(
        self,
        left: Image,
        right: Image,
        *,
        calibration: Calibration | None = None,
        frame: Literal["rectified", "original"] | None = None,
        deadline_ms: int | None = None,
        **options: Unpack[Options],
    ) -> DisparityResult:
        """`StereoClient.disparity`, awaited."""
        request = _request("npz", left, right, calibration, deadline_ms, options, frame=frame)
        return await self._post(request, _disparity_result)

    async def point_cloud(
        self,
        left: Image,
        right: Image,
        *,
        calibration: Calibration | None = None,
        max_uncertainty: float | None = None,
        cx_px: float | None = None,
        cy_px: float | None = None,
        deadline_ms: int | None = None,
        **options: Unpack[Options],
    ) -> PointCloud:
        """`StereoClient.point_cloud`, awaited."""
        request = _request(
            "ply",
            left,
            right,
            calibration,
            deadline_ms,
            options,
            max_uncertainty=max_uncertainty,
            cx_px=cx_px,
            cy_px=cy_px,
        )
        return await self._post(request, _point_cloud)

    def stream(
        self, *, warm_iters: int | tuple[int, int, int] | None = None, **options: Unpack[Options]
    ) -> AsyncDisparityStream:
        """`StereoClient.stream` for asyncio (`async with` it)."""
        url = _stream_url(self._http, _query("npz", options, warm_iters=warm_iters))
        return AsyncDisparityStream(url, self._http.headers.get("Authorization"), self._http.timeout.read)

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

    async def _post(self, request: dict[str, Any], read: Callable[[bytes], Result]) -> Result:
        """`StereoClient._post`, awaited."""
        for attempt in count():
            try:
                return read(_answered(await self._http.post("/disparity", **request)))
            except ServiceError as error:
                wait = self._retries.wait_for(error, attempt)
                if wait is None:
                    raise
                await asyncio.sleep(wait)
        raise AssertionError("unreachable: the attempts never end")
