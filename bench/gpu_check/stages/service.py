"""The service stage: `python -m crestereo_pp.service` on loopback answering a real pair over HTTP and
a burst of concurrent requests (batches), each model; skipped where the service's packages are
missing."""

from __future__ import annotations

import argparse
import collections
import importlib.util
import time
from collections.abc import Callable
from typing import Any

from ..pairs import samples_for
from ..plans import Plan, StageResult

SERVICE_PACKAGES = {
    "fastapi": "fastapi",
    "uvicorn": "uvicorn",
    "pydantic": "pydantic",
    "python_multipart": "python-multipart",
    "httpx": "httpx",
    "prometheus_client": "prometheus-client",
}
"""Modules the service stage needs (module -> package), beyond torch and the project."""


def service_stage(plan: Plan, deadline: float, args: argparse.Namespace, save: Callable[..., None]) -> StageResult:
    """The service on loopback (CRESTEREO_DEVICE the plan's device, its models), asked by the Python
    client (`exchange`), then stopped."""
    missing = [package for module, package in SERVICE_PACKAGES.items() if importlib.util.find_spec(module) is None]
    if missing:
        return StageResult("skipped", f"skipped: {', '.join(missing)} not installed (carry wheels: --wheels)")
    from crestereo_pp.client import StereoClient
    from crestereo_pp.service.local import start_service

    origins = {module: getattr(importlib.util.find_spec(module), "origin", None) for module in SERVICE_PACKAGES}
    print(f"service packages from: {origins}", flush=True)
    height, width = plan.sizes[0]
    sample = samples_for(args.data, 1, height, width, "cpu")[0][0]

    settings = {
        "CRESTEREO_DEVICE": plan.device,
        "CRESTEREO_MODELS": ",".join(plan.service_models),
        "CRESTEREO_MAX_BATCH_PIXELS": str(8 * 480 * 1248),
        "CRESTEREO_LOG_LEVEL": "warning",
    }
    try:
        server = start_service(settings, ready_timeout_s=max(1.0, deadline - 15 - time.monotonic()))
    except RuntimeError as error:
        return StageResult("failed", f"the service did not become ready ({error})")
    try:
        timeout_s = max(10.0, deadline - time.monotonic())
        with StereoClient(server.base_url, timeout_s=timeout_s, max_retries=0) as client:
            data = exchange(client, plan, sample)
    finally:
        server.stop()
    problems = data.pop("problems")
    detail = f"{data['requests']} requests on {plan.device}, batch sizes {data['batch_sizes']}"
    return StageResult("failed" if problems else "passed", "; ".join(problems) or detail, data=data)


def exchange(client: Any, plan: Plan, sample: Any) -> dict[str, Any]:
    """Requests to the ready service through `client` (a `client.StereoClient`): one per model,
    then `service_requests` concurrent lite ones; checks each answer (shapes, finite non-negative
    disparity, uncertainty in [0, 1])."""
    import numpy as np
    from service_load import concurrently  # bench/'s sibling script: the load benchmark's bursts

    from crestereo_pp.client import ServiceError

    known = sample.valid & np.isfinite(sample.disparity)
    iters = tuple(plan.iters) if plan.iters else None
    problems: list[str] = []
    epe: dict[str, float] = {}
    compute_ms: dict[str, list[float]] = collections.defaultdict(list)
    batch_sizes: list[int] = []

    def ask(model: str) -> None:
        try:
            result = client.disparity(sample.left, sample.right, model=model, iters=iters)
        except ServiceError as error:
            problems.append(f"{model}: HTTP {error.status} {error.code}: {error.message[:200]}")
            return
        disparity, uncertainty = result.disparity, result.uncertainty
        if disparity.shape != sample.disparity.shape or uncertainty.shape != disparity.shape:
            problems.append(f"{model}: maps of shape {disparity.shape}, not {sample.disparity.shape}")
        elif not (np.isfinite(disparity).all() and (disparity >= 0).all() and disparity.std() > 0):
            problems.append(f"{model}: disparity not finite, negative or constant")
        elif not ((uncertainty >= 0) & (uncertainty <= 1)).all():
            problems.append(f"{model}: uncertainty outside [0, 1]")
        else:
            epe[model] = round(float(np.abs(disparity - sample.disparity)[known].mean()), 3)
        compute_ms[model].append(result.compute_ms)
        batch_sizes.append(result.batch_size)

    for model in plan.service_models:
        for _ in range(2):  # the second request of a shape replays a CUDA graph
            ask(model)
    concurrently(lambda _: ask(plan.service_models[0]), plan.service_requests, plan.service_requests)
    return dict(
        pair=sample.name,
        size=list(sample.disparity.shape),
        requests=len(batch_sizes),
        batch_sizes=sorted(set(batch_sizes)),
        epe_px=epe,
        compute_ms={m: [round(t, 1) for t in times] for m, times in compute_ms.items()},
        problems=problems,
    )
