"""Service settings, read once from `CRESTEREO_*` environment variables.

Every field of `Settings` is one variable: the field name upper-cased with the `CRESTEREO_`
prefix (`max_batch_size` -> `CRESTEREO_MAX_BATCH_SIZE`). `service/README.md` documents each one;
a test keeps that table and this class in step.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from crestereo_pp.inference.backend_choice import BackendChoice, PrecisionChoice
from crestereo_pp.inference.openvino_backend import MAX_COMPILED_BYTES
from crestereo_pp.inference.options import Iterations, parse_iterations
from crestereo_pp.model.config import MODEL_NAMES, ModelName
from crestereo_pp.service import DEFAULT_MAX_IMAGE_PIXELS

ENV_PREFIX = "CRESTEREO_"


def _default_model_max_pixels() -> dict[ModelName, int]:
    return {"full": 1_048_576}


class Settings(BaseModel):
    """Everything the service can be configured with; immutable once the app is created."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    models: tuple[ModelName, ...] = Field(
        MODEL_NAMES, min_length=1, description="Comma-separated models to load at startup."
    )
    weights: dict[ModelName, Path] = Field(
        default_factory=dict,
        description="Weights file per model as `name=path,...`; a model not listed loads its "
        "packaged weights (`model/weights/<name>.pt`, random initialisation when absent).",
    )
    device: str = Field("cpu", description="Torch device the models run on.")
    backend: BackendChoice = Field(
        "auto",
        description="`openvino`: the networks compiled for the CPU (2-3x faster than torch); `torch`: eager "
        "(CUDA graphs on a GPU); `auto`: OpenVINO on a CPU, torch on a GPU. OpenVINO runs the iteration "
        "settings whose graphs are in `CRESTEREO_CACHE_DIR` (see `export_iters`); torch answers the others.",
    )
    precision: PrecisionChoice = Field(
        "auto",
        description="`bf16`: OpenVINO in bf16, or torch under bf16 autocast (maps stay float32); `fp32`; "
        "`auto`: bf16 for OpenVINO on a CPU that computes bf16 natively (AMX, AVX512-BF16), else fp32.",
    )
    cache_dir: Path | None = Field(
        None,
        description="Where OpenVINO keeps its compiled graphs, so that a restart does not compile again; "
        "(none): `$XDG_CACHE_HOME/crestereo-pp`, else `~/.cache/crestereo-pp`.",
    )
    compiled_mb: int = Field(
        MAX_COMPILED_BYTES >> 20,
        ge=1,
        description="Memory (MiB, estimated) for OpenVINO's compiled image shapes, per model: each new padded shape "
        "is compiled on first use (about a second) and kept, the least recently used dropped first. The default "
        "holds every shape one camera's pairs need at the largest size the default inference enlarges them to; "
        "under less, a camera's shapes can evict one another and its requests compile again each time.",
    )
    export_iters: tuple[str, ...] | None = Field(
        None,
        max_length=4,
        description="Iteration settings whose OpenVINO graphs (cold and warm starts) the service exports at "
        "startup, in the background, one at a time: up to four, space-separated, each `N` or `N16,N8,N4`, "
        "or `default` for each model's own; torch computes them until each is ready (logged with its time). "
        "Requests with other iterations run on torch and export nothing. Graphs in `CRESTEREO_CACHE_DIR` are "
        "used either way.",
    )
    threads: int = Field(
        0,
        ge=0,
        description="Torch intra-op threads; 0 = the container's CPU quota (cgroup), else the number of usable cores.",
    )
    max_batch_size: int = Field(8, ge=1, description="Most requests computed together in one batch.")
    max_batch_pixels: int = Field(
        131_072,
        ge=1,
        description="Most padded pixels (batch size x height x width) in one batch; "
        "a single larger image still runs, alone. The default suits a small CPU, where batching "
        "pays only while images are small (see service/README.md).",
    )
    max_wait_ms: float = Field(
        10.0,
        ge=0,
        description="Longest a partial batch is held back while more requests are being "
        "received, or while full batches run first; an idle server runs a lone request at once.",
    )
    max_queue: int = Field(
        32,
        ge=1,
        description="Requests admitted per model and not yet computing (decoding or "
        "queued); beyond it `/disparity` answers 503 with `Retry-After`.",
    )
    max_requests: int = Field(
        48,
        ge=1,
        description="Most requests in progress at once (uploads being received included; the `/health` probes "
        "are never counted); beyond it 503 `overloaded` with `Retry-After`. With `max_body_bytes` it bounds the "
        "memory that request bodies can hold.",
    )
    max_body_bytes: int = Field(32 * 1024 * 1024, ge=1, description="Largest request body in bytes (413 beyond).")
    max_upload_bytes: int = Field(
        192 * 1024 * 1024,
        ge=1,
        description="Most bytes of request bodies held at once (a body counts from its `Content-Length` before it "
        "is read, else as it arrives); beyond it 503 `overloaded` with `Retry-After`. Stream images have their own "
        "budget (`max_stream_bytes`). At least `max_body_bytes`. The default holds six of the largest bodies, or "
        "`max_requests` pairs of 4 MiB.",
    )
    max_stream_bytes: int = Field(
        64 * 1024 * 1024,
        ge=1,
        description="Most bytes of stream images held at once, all streams together, apart from the request "
        "bodies' `max_upload_bytes`: an image counts from its arrival until its pair is answered; a stream whose "
        "image does not fit is closed with 1013 `overloaded`. At least twice `max_stream_image_bytes`, so that a "
        "whole pair fits; the default holds four pairs of the largest stream images, or `max_streams` pairs of "
        "2 MiB.",
    )
    max_stream_image_bytes: int = Field(
        16 * 1024 * 1024,
        ge=1,
        description="Largest image file of a stream (one WebSocket message), and never more than the largest file "
        "of an image within the model's pixel limit (8 bytes a pixel plus 1 MiB, at most `max_body_bytes`): "
        "uvicorn closes a larger message with 1009 before the app sees it (`ws_max_size`), the stream one over its "
        "model's limit with 1009 `image_too_large`. Smaller than a request body: uvicorn reads each open stream's "
        "next message whole, outside `max_stream_bytes`.",
    )
    client_error_rate: float = Field(
        10.0,
        gt=0,
        description="Client errors (4xx answers) a second that one client address may have answered at once, "
        "after a first `client_error_burst`; past it each error answer is held back until the address is "
        "within its rate again (at most 2 s), so that a client repeating bad requests as fast as it can does not "
        "take the CPU from good ones. Successful answers are never held back.",
    )
    client_error_burst: int = Field(
        100,
        ge=1,
        description="Client errors one client address may have answered at once before `client_error_rate` applies.",
    )
    max_streams: int = Field(
        16,
        ge=1,
        description="Most `/disparity/stream` connections open at once; beyond it the handshake is refused with "
        "HTTP 503 `overloaded` and `Retry-After`.",
    )
    max_streams_per_client: int = Field(
        4,
        ge=1,
        description="Most streams open at once from one client address (as uvicorn sees it: behind a proxy, "
        "let uvicorn read `X-Forwarded-For` with `FORWARDED_ALLOW_IPS`); beyond it HTTP 503 `overloaded`.",
    )
    stream_idle_timeout_s: float = Field(
        5.0,
        gt=0,
        description="Longest a stream waits for its next image: a pair's left image (then it is closed, 1000) or "
        "its right one (1008 `body_timeout`). As long as uvicorn keeps an idle HTTP connection: a camera sends "
        "its next pair well within it, and an idle stream gives back its place and memory soon.",
    )
    max_image_pixels: int = Field(
        DEFAULT_MAX_IMAGE_PIXELS,
        ge=1,
        description="Largest image (width x height), checked from the file header before decoding (413 beyond).",
    )
    model_max_pixels: dict[ModelName, int] = Field(
        default_factory=_default_model_max_pixels,
        description="Per-model image limits below `max_image_pixels`, as `name=pixels,...` (413 "
        "beyond). On a 2-core CPU a 2048x2048 pair took 306 s and 7.9 GB on `full`, 78 s and "
        "3.5 GB on `lite`: the default keeps one `full` request near a minute (1 MP).",
    )
    max_request_cost: float = Field(
        4.0,
        ge=1.0,
        description="Most compute one request may ask for, in plain requests (the model's iterations, one "
        "pass, no flip, scale 1) of the model's largest image: its pixels times what its options cost "
        "(iterations, `two_pass`, `scale`, `flip`); 422 `request_too_costly` beyond, before its images are "
        "decoded. One inference thread computes every request, so this bounds how long one request can hold "
        "it: `iters=99,99,99&flip=true` counts as 29.5 plain requests, 74 where no graph is ready for those "
        "iterations and torch computes them.",
    )
    min_image_side: int = Field(32, ge=1, description="Smallest image width or height (422 below).")
    body_timeout_s: float = Field(
        60.0, gt=0, description="Longest a request body may take to arrive (408 beyond), from the end of its headers."
    )
    decode_workers: int = Field(
        2,
        ge=1,
        description="Decoder processes: uploads are parsed and decoded there, a few at a time, never in the server.",
    )
    decode_memory_mb: int = Field(
        768,
        ge=64,
        description="Memory (address space, MiB) a decoder process may use for one upload beyond its own "
        "start-up size; an upload needing more is answered 413 `decode_too_large`.",
    )
    decode_cpu_s: float = Field(
        5.0,
        gt=0,
        description="CPU seconds a decoder process may spend on one step of reading an upload (parsing the "
        "form, or decoding both images); beyond it 422 `decode_too_costly`.",
    )
    rectifier_cache_mb: int = Field(
        256,
        ge=1,
        description="Memory (MiB) for the rectification maps of raw pairs' cameras, those in use and those kept "
        "for the next requests of the same camera (a 2048x2048 camera's take 96 MiB; the least recently used "
        "goes first). A request whose camera's maps do not fit waits for room, under its deadline.",
    )
    min_timeout_ms: int = Field(
        100,
        ge=1,
        description="Shortest `X-Request-Timeout-Ms` taken: a shorter deadline cannot be met by any request, and "
        "is answered 503 `deadline_exceeded` at once, before the body is read.",
    )
    api_key: str | None = Field(
        None,
        description="When set, every route requires `Authorization: Bearer <key>` but the health probes, metrics, "
        "the page, its static files, `/docs` and `/openapi.json`.",
    )
    drain_timeout_s: float = Field(
        30.0,
        ge=0,
        description="After SIGTERM, how long admitted requests may still be computed; "
        "those left (queued or computing) then get 503 `draining`.",
    )
    log_level: Literal["debug", "info", "warning", "error"] = Field(
        "info", description="Level of the JSON logs on stderr."
    )

    @model_validator(mode="after")
    def _budget_holds_a_body(self) -> Settings:
        if self.max_upload_bytes < self.max_body_bytes:
            raise ValueError("max_upload_bytes must be at least max_body_bytes, or the largest bodies are never taken")
        return self

    @model_validator(mode="after")
    def _stream_budget_holds_a_pair(self) -> Settings:
        if self.max_stream_bytes < 2 * self.max_stream_image_bytes:
            raise ValueError(
                "max_stream_bytes must be at least twice max_stream_image_bytes, or a pair of the largest stream "
                "images is never taken"
            )
        return self

    @field_validator("models", mode="before")
    @classmethod
    def _split_models(cls, value: object) -> object:
        if isinstance(value, str):
            return tuple(name.strip() for name in value.split(",") if name.strip())
        return value

    @field_validator("weights", "model_max_pixels", mode="before")
    @classmethod
    def _split_per_model(cls, value: object) -> object:
        if isinstance(value, str):
            return dict(_name_value_pairs(value))
        return value

    @field_validator("export_iters", mode="before")
    @classmethod
    def _split_iterations(cls, value: object) -> object:
        if isinstance(value, str):
            return tuple(value.split()) or None
        return value

    @field_validator("export_iters")
    @classmethod
    def _check_iterations(cls, value: tuple[str, ...] | None) -> tuple[str, ...] | None:
        for iters in value or ():
            if iters != "default":
                parse_iterations(iters)  # ValueError where invalid
        return value

    def export_iterations(self) -> tuple[Iterations, ...]:
        """`export_iters` as `Iterations` (None: the model's)."""
        return tuple(None if iters == "default" else parse_iterations(iters) for iters in self.export_iters or ())

    @field_validator("api_key", mode="before")
    @classmethod
    def _empty_key_is_none(cls, value: object) -> object:
        return None if value == "" else value

    def pixel_limit(self, model: str) -> int:
        """Largest image (width x height) accepted for `model`."""
        limits: dict[str, int] = dict(self.model_max_pixels.items())  # looked up by any name
        return min(self.max_image_pixels, limits.get(model, self.max_image_pixels))

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> Settings:
        """Settings from `CRESTEREO_<FIELD>` variables; unset ones keep their defaults."""
        environ = os.environ if environ is None else environ
        values = {
            name: environ[ENV_PREFIX + name.upper()]
            for name in cls.model_fields
            if ENV_PREFIX + name.upper() in environ
        }
        return cls.model_validate(values)


def _name_value_pairs(text: str) -> list[tuple[str, str]]:
    """ "a=1, b=2" -> [("a", "1"), ("b", "2")] (the form of the per-model settings)."""
    pairs = [item.split("=", 1) for item in text.split(",") if item.strip()]
    if any(len(pair) != 2 for pair in pairs):
        raise ValueError("expected name=value[,name=value]")
    return [(name.strip(), value.strip()) for name, value in pairs]
