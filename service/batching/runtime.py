"""What one running service owns: settings, metrics, loaded models, the inference thread and its batcher."""

from __future__ import annotations

import asyncio
import logging
import signal
import threading
from collections.abc import Callable, Coroutine
from functools import partial
from pathlib import Path
from types import FrameType
from typing import Any

from crestereo_pp.service.api.errors import ApiError, bad_input, draining
from crestereo_pp.service.api.metrics import Metrics
from crestereo_pp.service.api.schemas import BatchingConfig, HealthResponse, ModelStatus, ServiceState
from crestereo_pp.service.batching.batcher import Batcher, Draining
from crestereo_pp.service.batching.cpu import configure_torch_threads, usable_cpus
from crestereo_pp.service.batching.daemon_thread import DaemonThreadExecutor
from crestereo_pp.service.batching.stereo import Predictor, StereoBatches, StereoKey, StereoMaps, StereoPair
from crestereo_pp.service.settings import Settings
from crestereo_pp.service.uploads.rectifiers import RectifierCache
from crestereo_pp.service.uploads.sandbox import DecoderLimits, DecoderPool

logger = logging.getLogger(__name__)

ModelLoader = Callable[..., Predictor]  # called as inference.load_model is: loader(name, weights=..., device=..., ...)


StereoBatcher = Batcher[StereoKey, StereoPair, StereoMaps]
"""The service's batcher: stereo pairs in, their maps out."""


def weights_identity(predictor: Predictor) -> str:
    """First 16 hex digits of the weights' sha256, or `random-init`."""
    return predictor.weights_sha256[:16] if predictor.weights_sha256 else "random-init"


class ServiceRuntime:
    """Lifecycle: `start()` loads the models on the inference thread in the background (the service
    answers 503 `loading` meanwhile), then batching starts (`ready`). SIGTERM switches to
    `draining`: nothing new is admitted and admitted work has `drain_timeout_s` to finish."""

    def __init__(self, settings: Settings, loader: ModelLoader) -> None:
        self.settings = settings
        self.metrics = Metrics(settings.max_batch_size)
        self.state: ServiceState = "loading"
        self.torch_threads = settings.threads or usable_cpus()
        self.predictors: dict[str, Predictor] = {}
        self.batcher: StereoBatcher | None = None
        self.decoders = DecoderPool(
            DecoderLimits(settings.decode_workers, settings.decode_memory_mb << 20, settings.decode_cpu_s)
        )
        self.rectifiers = RectifierCache(settings.rectifier_cache_mb << 20)  # raw pairs: one per calibration
        self.drain_over = asyncio.Event()  # set when the drain timeout has passed
        self._load_finished = asyncio.Event()  # set when the models loaded, or failed to
        self._loader = loader
        self._executor: DaemonThreadExecutor | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._previous_sigterm: Callable[[int, FrameType | None], object] | None = None

    async def start(self) -> None:
        await self.decoders.start()
        configure_torch_threads(self.torch_threads)
        # The single inference thread owns the CPU: it loads the models and computes every batch.
        self._executor = DaemonThreadExecutor(
            "inference", initializer=configure_torch_threads, initargs=(self.torch_threads,)
        )
        self._spawn(self._load_models())
        self._hook_sigterm()

    async def stop(self) -> None:
        self._unhook_sigterm()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if self.batcher is not None:
            await self.batcher.close()
        await self.decoders.close()
        if self._executor is not None:  # a batch abandoned at the drain timeout is not waited for
            await asyncio.to_thread(self._executor.shutdown, wait=not self._executor.busy, cancel_futures=True)

    async def models_loaded(self) -> None:
        """Return once the models are loaded (RuntimeError where they failed to load)."""
        await self._load_finished.wait()
        if self.state == "failed":
            raise RuntimeError("models failed to load; see the log above")

    def begin_drain(self) -> None:
        """Stop admitting work; after `drain_timeout_s`, answer what is still queued or computing
        503 `draining` (a computing batch is abandoned), so that shutdown takes no longer."""
        if self.state == "draining":
            return
        logger.info("draining", extra={"drain_timeout_s": self.settings.drain_timeout_s})
        self.state = "draining"
        if self.batcher is not None:
            self.batcher.begin_drain()
            self._spawn(self._expire_drain(self.batcher))

    def batcher_for(self, model: str) -> StereoBatcher:
        """The batcher that computes `model`'s requests; the error to answer where there is none
        (503 while loading, draining or failed; 422 for a model this server did not load)."""
        if self.state == "failed":
            raise ApiError(
                503,
                "unavailable",
                "models failed to load; see the server log",
                reject_reason="not_ready",
                headers={"Retry-After": "60"},
            )
        if self.state == "draining":
            raise draining("server is shutting down")
        if self.state == "loading" or self.batcher is None:
            raise ApiError(
                503, "loading", "models are still loading", reject_reason="not_ready", headers={"Retry-After": "5"}
            )
        if model not in self.predictors:
            raise bad_input(
                422,
                "model_not_loaded",
                f"model `{model}` is not loaded by this server (loaded: {', '.join(self.predictors)})",
            )
        return self.batcher

    @property
    def is_alive(self) -> bool:
        """False when the process should be restarted: models failed to load or the inference thread died."""
        return self.state != "failed" and (self.batcher is None or self.batcher.is_running)

    def health(self) -> HealthResponse:
        depths = self.batcher.queue_depths() if self.batcher else {}
        return HealthResponse(
            status=self.state,
            models={name: self._model_status(name) for name in self.settings.models},
            queue_depth={name: depths.get(name, 0) for name in self.settings.models},
            batching=BatchingConfig(
                max_batch_size=self.settings.max_batch_size,
                max_batch_pixels=self.settings.max_batch_pixels,
                max_wait_ms=self.settings.max_wait_ms,
                max_queue=self.settings.max_queue,
                torch_threads=self.torch_threads,
            ),
        )

    def _model_status(self, name: str) -> ModelStatus:
        predictor = self.predictors.get(name)
        if predictor is None:
            return ModelStatus(loaded=False)
        return ModelStatus(loaded=True, parameters=predictor.num_parameters, weights=weights_identity(predictor))

    async def _load_models(self) -> None:
        loop = asyncio.get_running_loop()
        try:
            for name in self.settings.models:
                weights: Path | None = self.settings.weights.get(name)
                self.predictors[name] = await loop.run_in_executor(
                    self._executor,
                    partial(
                        self._loader,
                        name,
                        weights=weights,
                        device=self.settings.device,
                        backend=self.settings.backend,
                        precision=self.settings.precision,
                        cache_dir=self.settings.cache_dir,
                        compiled_bytes=self.settings.compiled_mb << 20,
                        prepare_iters=self.settings.export_iterations(),
                    ),
                )
                logger.info(
                    "model loaded",
                    extra={
                        "model": name,
                        "parameters": self.predictors[name].num_parameters,
                        "weights": weights_identity(self.predictors[name]),
                        "backend": self.predictors[name].backend,
                        "precision": self.predictors[name].precision,
                        "compiled": self.predictors[name].ready(),
                    },
                )
        except Exception:
            logger.exception("model loading failed; the service stays unready")
            self.state = "failed"
            self._load_finished.set()
            return
        assert self._executor is not None
        self.batcher = Batcher(self.settings, StereoBatches(self.predictors), self._executor, self.metrics)
        self.batcher.start()
        if self.state == "loading":
            self.state = "ready"
            logger.info("ready: computing requests", extra={"models": list(self.predictors)})
        else:  # SIGTERM came while loading
            self.batcher.begin_drain()
        self._load_finished.set()

    async def _expire_drain(self, batcher: StereoBatcher) -> None:
        await asyncio.sleep(self.settings.drain_timeout_s)
        self.drain_over.set()
        batcher.abandon(Draining("drain timeout reached before this request was computed"))

    def _spawn(self, coroutine: Coroutine[Any, Any, None]) -> None:
        task = asyncio.create_task(coroutine)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _hook_sigterm(self) -> None:
        """Chain in front of the server's own SIGTERM handler (uvicorn's stops the listener and
        waits for in-flight requests), so that readiness turns 503 at once. Only done where a
        server owns SIGTERM; a bare process keeps the default handler."""
        previous = signal.getsignal(signal.SIGTERM)
        if threading.current_thread() is not threading.main_thread() or not callable(previous):
            return
        loop = asyncio.get_running_loop()

        def on_sigterm(signum: int, frame: FrameType | None) -> None:
            loop.call_soon_threadsafe(self.begin_drain)
            previous(signum, frame)

        signal.signal(signal.SIGTERM, on_sigterm)
        self._previous_sigterm = previous

    def _unhook_sigterm(self) -> None:
        if self._previous_sigterm is not None:
            signal.signal(signal.SIGTERM, self._previous_sigterm)
            self._previous_sigterm = None
