"""The bench stage: the inference table (`StereoPredictor.predict_batch` as the service calls it, per
model and size: one pass per batch, precision and CUDA graphs, and the default inference;
`row_settings`), then bf16 against fp32 and graph replay against eager on the dev pairs."""

from __future__ import annotations

import argparse
import itertools
import json
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from timing import timed_calls  # bench/'s sibling script (standard library only)

from ..pairs import samples_for
from ..plans import Plan, StageResult

ROW_SECONDS = 5.0
"""A benchmark row stops timing after this long once it has MIN_TIMED_CALLS calls."""
MIN_TIMED_CALLS = 3


def bench_stage(plan: Plan, deadline: float, args: argparse.Namespace, save: Callable[..., None]) -> StageResult:
    """The inference table's rows (bench_row) and each model's accuracy row (accuracy), saved after
    each row; rows left when 20 s remain are recorded as not measured."""
    import torch

    from crestereo_pp.inference import load_model

    device = torch.device(plan.device)
    on_cuda = device.type == "cuda"
    data: dict[str, Any] = {
        "device": torch.cuda.get_device_name(device) if on_cuda else f"CPU ({os.cpu_count()} cores)",
        "iters": plan.iters,
        "warmup_calls": plan.warmup_calls,
        "rows": [],
        "accuracy": [],
    }
    for name in plan.models:
        eager = load_model(name, device=device, cuda_graphs=False)
        graphed = load_model(name, device=device) if on_cuda else None
        for height, width in plan.sizes:
            samples, _ = samples_for(None, max(plan.batches), height, width, device)
            for batch, graphs, precision, two_pass in row_settings(plan, on_cuda):
                row: dict[str, Any] = dict(model=name, size=f"{height}x{width}", batch=batch, precision=precision)
                row.update(graphs=graphs, two_pass=two_pass)
                if time.monotonic() > deadline - 20:
                    row["skipped"] = "not measured: out of time"
                else:
                    row.update(bench_row(plan, eager, graphed, graphs, precision, two_pass, samples[:batch]))
                data["rows"].append(row)
                print(json.dumps(row), flush=True)
                save(StageResult("running", f"{len(data['rows'])} rows", data=data))
        if time.monotonic() < deadline - 20:
            data["accuracy"].append(accuracy(plan, name, eager, graphed, args.data, deadline))
            print(json.dumps(data["accuracy"][-1]), flush=True)
        del eager, graphed
        if on_cuda:
            torch.cuda.empty_cache()
    measured = [r for r in data["rows"] if "skipped" not in r]
    late = [r for r in data["rows"] if r.get("skipped", "").startswith("not measured")]
    complete = not late and len(data["accuracy"]) == len(plan.models)
    detail = f"{len(measured)} of {len(data['rows'])} rows measured; accuracy of {len(data['accuracy'])} models"
    return StageResult("passed" if complete and measured else "failed", detail, data=data)


def row_settings(plan: Plan, on_cuda: bool) -> list[tuple[int, bool, str, bool | str]]:
    """The rows' (batch, CUDA graphs, precision, two_pass) for one model and size: every batch,
    graphs or not and precision in one pass at the pair's size (``two_pass=False``: the network
    once, as the paper times it), then the default inference (``two_pass="auto"``: a quick pass,
    then one or two passes on the pair enlarged as far as its disparities allow, the blend with SGBM
    and the edges' refinement, on the CPU) at batch 1 in bf16, with graphs where there is
    CUDA: what a user's single request costs."""
    one_pass = [
        (batch, graphs, precision, False)
        for batch, graphs, precision in itertools.product(plan.batches, (False, True), ("fp32", "bf16"))
    ]
    return [*one_pass, (1, on_cuda, "bf16", "auto")]


def bench_row(
    plan: Plan, eager: Any, graphed: Any, graphs: bool, precision: str, two_pass: bool | str, samples: list[Any]
) -> dict[str, Any]:
    """One row's numbers (see time_predict_batch), or why there are none. A graphed row's graphs
    are dropped after it, so that each row's peak memory is its own."""
    lefts, rights = [s.left for s in samples], [s.right for s in samples]
    if not graphs:
        return time_predict_batch(eager, precision, two_pass, lefts, rights, plan)
    if graphed is None:
        return {"skipped": "n/a: CUDA graphs need CUDA"}
    numbers = time_predict_batch(graphed, precision, two_pass, lefts, rights, plan)
    graphed.graphs.clear()
    return numbers


def time_predict_batch(
    predictor: Any, precision: str, two_pass: bool | str, lefts: list[Any], rights: list[Any], plan: Plan
) -> dict[str, Any]:
    """Median wall time of up to plan.timed_runs calls of predict_batch(lefts, rights) at
    `precision` with `two_pass` (after plan.warmup_calls; at least MIN_TIMED_CALLS, then while under
    ROW_SECONDS; timing.py's `timed_calls`), peak device memory, and how many of the timed calls
    replayed a CUDA graph. lefts, rights: the batch's uint8 HxWx3 RGB views."""
    import torch

    predictor.precision = precision
    on_cuda = predictor.device.type == "cuda"
    if on_cuda:
        torch.cuda.reset_peak_memory_stats(predictor.device)

    def call() -> None:
        # numpy out: the copy waits; one pass is the network alone, auto the default (with its host steps)
        predictor.predict_batch(
            lefts,
            rights,
            iters=plan.iters,
            two_pass=two_pass,
            blend_sgbm=two_pass == "auto",
            refine_edges=two_pass == "auto",
            align_rows=two_pass == "auto",
        )

    for _ in range(plan.warmup_calls):
        call()
    replays_before = predictor.graphs.replays if predictor.graphs is not None else 0
    times = timed_calls(call, plan.timed_runs, max_seconds=ROW_SECONDS, min_runs=MIN_TIMED_CALLS)
    median_s = statistics.median(times)
    return dict(
        ms_per_batch=1000 * median_s,
        ms_per_pair=1000 * median_s / len(lefts),
        pairs_per_s=len(lefts) / median_s,
        peak_mib=round(torch.cuda.max_memory_allocated(predictor.device) / 2**20) if on_cuda else None,
        replays=f"{(predictor.graphs.replays - replays_before) if predictor.graphs is not None else 0}/{len(times)}",
    )


def accuracy(plan: Plan, name: str, eager: Any, graphed: Any, data_dir: Path | None, deadline: float) -> dict[str, Any]:
    """bf16 against fp32 and graph replay against eager on the dev pairs (or procedural scenes)."""
    import numpy as np

    from crestereo_pp.inference import NETWORK_ONLY

    height, width = plan.sizes[0]
    samples, source = samples_for(data_dir, plan.accuracy_pairs, height, width, eager.device)
    bf16_differences: list[float] = []
    graph_differences: list[float] = []
    epe_fp32: list[float] = []
    epe_bf16: list[float] = []
    for sample in samples:
        if bf16_differences and time.monotonic() > deadline - 20:
            break
        known = sample.valid & np.isfinite(sample.disparity)
        eager.precision = "fp32"
        fp32 = eager.predict(sample.left, sample.right, iters=plan.iters, **NETWORK_ONLY).disparity
        eager.precision = "bf16"
        bf16 = eager.predict(sample.left, sample.right, iters=plan.iters, **NETWORK_ONLY).disparity
        bf16_differences.append(float(np.abs(bf16 - fp32).mean()))
        epe_fp32.append(float(np.abs(fp32 - sample.disparity)[known].mean()))
        epe_bf16.append(float(np.abs(bf16 - sample.disparity)[known].mean()))
        if graphed is not None:
            graphed.precision = "fp32"
            for _ in range(2):  # the second sighting of the shape is captured and replayed
                replayed = graphed.predict_batch([sample.left], [sample.right], iters=plan.iters, **NETWORK_ONLY)[
                    0
                ].disparity
            graph_differences.append(float(np.abs(replayed - fp32).max()))
            graphed.graphs.clear()
    return dict(
        model=name,
        pairs=len(bf16_differences),
        source=source,
        bf16_mean_abs_px=float(np.mean(bf16_differences)),
        graph_max_abs_px=max(graph_differences) if graph_differences else None,
        epe_fp32=float(np.mean(epe_fp32)),
        epe_bf16=float(np.mean(epe_bf16)),
    )
