"""The service as a Ray Serve application: the same FastAPI app in each replica, replicas across a
Ray cluster, Ray's HTTP proxy in front (`crestereo-pp serve --ray`).

Each replica is one `create_app(...)` with its own batcher, decoder processes, limits and
metrics; it joins the routing only once its models are loaded, and Ray replaces it where its
liveness fails. Ray is an optional dependency (`pip install 'crestereo-pp[ray]'`): nothing else in
the service imports this module.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from dataclasses import dataclass
from types import FrameType
from typing import Any

from fastapi import FastAPI
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from crestereo_pp.service.api.app import create_app
from crestereo_pp.service.ray.cluster import connect, cpu_share, cpu_threads, node_cpus, require_ray
from crestereo_pp.service.settings import ENV_PREFIX, Settings

APP_NAME = "crestereo-pp"
REPLICA_HEADER = "X-Replica"
PROXY_CALLBACK = "crestereo_pp.service.ray.proxy.proxy_middlewares"
"""Import path of the callback that gives Ray's HTTP proxy its middleware."""

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Scale:
    """How many replicas, and each one's CPU share (its torch threads).

    replicas: a fixed count (None: 1), or min_replicas..max_replicas for autoscaling on ongoing
    requests. cpus: CPUs reserved per replica in the Ray cluster; None: an equal share of the
    cluster's CPUs for the most replicas, a fraction of a CPU where they outnumber the CPUs
    (`cpu_share`).
    """

    replicas: int | None = None
    min_replicas: int | None = None
    max_replicas: int | None = None
    cpus: int | None = None

    def __post_init__(self) -> None:
        autoscaled = self.min_replicas is not None or self.max_replicas is not None
        if autoscaled and self.replicas is not None:
            raise ValueError("give --replicas, or --min-replicas and --max-replicas, not both")
        if autoscaled and (self.min_replicas is None or self.max_replicas is None):
            raise ValueError("autoscaling needs both --min-replicas and --max-replicas")
        if self.min_replicas is not None and self.max_replicas is not None:
            if not 0 <= self.min_replicas <= self.max_replicas or self.max_replicas < 1:
                raise ValueError("need 0 <= --min-replicas <= --max-replicas and --max-replicas >= 1")
        if self.replicas is not None and self.replicas < 1:
            raise ValueError("--replicas must be at least 1")
        if self.cpus is not None and self.cpus < 1:
            raise ValueError("--replica-cpus must be at least 1")

    @property
    def autoscaled(self) -> bool:
        return self.max_replicas is not None

    @property
    def most_replicas(self) -> int:
        return self.max_replicas if self.max_replicas is not None else self.replicas or 1

    def cpus_per_replica(self) -> float:
        """The CPU share of one replica on the connected cluster."""
        return self.cpus if self.cpus is not None else cpu_share(self.most_replicas, node_cpus())


class ReplicaHeaderMiddleware:
    """Names the replica that computed each HTTP answer in `X-Replica`."""

    def __init__(self, app: ASGIApp, replica: str) -> None:
        self.app = app
        self.header = (REPLICA_HEADER.lower().encode(), replica.encode())

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def send_with_replica(message: Message) -> None:
            if message["type"] == "http.response.start":
                message["headers"] = [*message.get("headers", []), self.header]
            await send(message)

        await self.app(scope, receive, send_with_replica)


def _deployment() -> Any:
    """The Ray Serve deployment class (defined where Ray is installed)."""
    from ray import serve

    @serve.ingress()
    class StereoReplica:
        """One replica: the service's FastAPI app, its models loaded before it joins the routing."""

        def __init__(self, settings: Settings) -> None:
            self.settings = settings
            self.replica = serve.get_replica_context().replica_id.unique_id
            self.fastapi: FastAPI | None = None

        def __serve_build_asgi_app__(self) -> FastAPI:
            self.fastapi = create_app(self.settings, load_before_serving=True)
            self.fastapi.add_middleware(ReplicaHeaderMiddleware, replica=self.replica)
            return self.fastapi

        def check_health(self) -> None:
            """Ray's liveness check: a replica whose inference thread died is replaced."""
            if self.fastapi is not None and not self.fastapi.state.runtime.is_alive:
                raise RuntimeError("the inference thread stopped; this replica is replaced")

    return StereoReplica


def build_application(settings: Settings, scale: Scale, cpus: float) -> Any:
    """The bound Ray Serve application: `scale` replicas of `cpus` CPUs each, whose threads are
    those whole CPUs (at least 1); the replicas get this process's `CRESTEREO_*` variables
    (logging, cache)."""
    from ray import serve

    settings = settings.model_copy(update={"threads": cpu_threads(cpus)})
    options: dict[str, Any] = {
        "ray_actor_options": {"num_cpus": cpus, "runtime_env": {"env_vars": service_environment()}},
        # Each replica admits up to its own limit and answers its own 503s beyond it; Ray's proxy
        # queues at most `max_queue` more per replica and answers 503 with Retry-After beyond.
        "max_ongoing_requests": settings.max_requests,
        "max_queued_requests": settings.max_queue * scale.most_replicas,
        "graceful_shutdown_timeout_s": settings.drain_timeout_s,
        "health_check_period_s": 5,
    }
    if not scale.autoscaled:
        options["num_replicas"] = scale.most_replicas
    else:
        options["autoscaling_config"] = {
            "min_replicas": scale.min_replicas,
            "max_replicas": scale.max_replicas,
            "target_ongoing_requests": settings.max_batch_size,
        }
    return serve.deployment(name="StereoReplica", **options)(_deployment()).bind(settings)


def app(args: dict[str, str]) -> Any:
    """Ray Serve's application builder, for `serve run crestereo_pp.service.ray.serve:app replicas=2`
    and for a config file (KubeRay's RayService: `import_path: crestereo_pp.service.ray.serve:app`).
    Arguments, all optional: `replicas`, or `min_replicas` and `max_replicas`; `replica_cpus`. The
    `CRESTEREO_*` variables of the process that builds it configure the replicas."""
    known = {"replicas", "min_replicas", "max_replicas", "replica_cpus"}
    if set(args) - known:
        raise ValueError(f"unknown arguments {sorted(set(args) - known)}; known: {sorted(known)}")
    numbers = {name: int(value) for name, value in args.items()}
    scale = Scale(
        numbers.get("replicas"), numbers.get("min_replicas"), numbers.get("max_replicas"), numbers.get("replica_cpus")
    )
    return build_application(Settings.from_env(), scale, scale.cpus_per_replica())


def service_environment() -> dict[str, str]:
    """The `CRESTEREO_*` variables of this process (the replicas get the same)."""
    return {name: value for name, value in os.environ.items() if name.startswith(ENV_PREFIX)}


def serve_on_ray(host: str, port: int, scale: Scale, address: str | None = None) -> None:
    """Run the service on Ray until SIGTERM or SIGINT, answering on host:port (Ray's proxy); the
    signals stop it also while its replicas start (slow to load, or waiting for CPUs).

    address: an existing cluster (`ray start --head` printed it; `auto` finds a local one), left
    running afterwards with this application removed; None: a local cluster of this machine's
    CPUs, started here and stopped again.
    """
    require_ray()
    import ray
    from ray import serve

    settings = Settings.from_env()  # checked here, before any cluster starts
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    # Read from the environment by the processes Ray starts: the proxy's middleware, and time for
    # the proxy to start on a busy machine (Ray's default of 5 s fails it there).
    os.environ["RAY_SERVE_HTTP_PROXY_CALLBACK_IMPORT_PATH"] = PROXY_CALLBACK
    os.environ.setdefault("RAY_SERVE_PROXY_READY_CHECK_TIMEOUT_S", "30")
    connect(address)
    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}  # after Ray's own
    try:
        cpus = scale.cpus_per_replica()
        serve.start(http_options={"host": host, "port": port})
        application = build_application(settings, scale, cpus)
        # Not serve.run: it waits for the replicas in a loop that a signal cannot end.
        serve.run_many(
            [serve.RunTarget(application, name=APP_NAME, route_prefix="/")], wait_for_applications_running=False
        )
        print(f"crestereo-pp: starting replicas of {cpus:g} CPU(s) each", flush=True)
        started = wait_until_running(stop)
        if started:
            logger.info(
                "serving on ray",
                extra={"url": f"http://{host}:{port}", "replicas": scale.most_replicas, "cpus_per_replica": cpus},
            )
            print(f"crestereo-pp: serving on http://{host}:{port} (Ray Serve, {cpus:g} CPU(s) per replica)", flush=True)
            while not stop.wait(0.5):
                pass
        print("crestereo-pp: stopping", flush=True)
        # Deleting the application gives each replica the drain timeout, even one Ray never placed:
        # not waited for where a start is cut short on a local cluster, which ray.shutdown() stops.
        if started or address is not None:
            serve.delete(APP_NAME)
        if started and address is None:
            serve.shutdown()  # type: ignore[no-untyped-call]
    finally:
        ray.shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def wait_until_running(stop: threading.Event) -> bool:
    """Wait until the application runs (True: every replica has loaded its models) or `stop` is
    set first (False); a RuntimeError where its deployment failed."""
    from ray import serve

    while not stop.wait(0.5):
        application = serve.status().applications[APP_NAME]
        if application.status == "RUNNING":
            return True
        if application.status == "DEPLOY_FAILED":
            raise RuntimeError(f"deploying {APP_NAME} failed: {application.message}")
    return False
