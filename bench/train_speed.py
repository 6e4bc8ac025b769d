"""Pairs per second of a lite training step on this machine, for the settings worth comparing.

    python bench/train_speed.py [--steps 12] [--rows today workers ...] [--profile ROW]

(On a GPU, bench/gpu_check's probe stage times `probe_rows` with the same `measure`.)

Every row runs in a fresh child process (its own OpenMP state): it builds the real
`training.trainer.Trainer` from the shipped lite weights and times --steps optimiser steps after
two warm-up steps, the batch fetch included (so data made on the critical path counts), as the
median seconds per step. The first row is the step as `crestereo-pp train` ran it before this
benchmark existed; `vs today` is the ratio of pairs/s to it. Quiet machine only: run it before
a training run starts, or pause the run.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Row:
    """One setting: TrainConfig overrides, and the process-level switches."""

    description: str
    overrides: dict[str, Any] = field(default_factory=dict)
    omp_wait_policy: str = "PASSIVE"
    wide_transposed: bool = True  # 1x15 gate convs computed as transposed 15x1 (model.update)


MIN_TIMED_STEPS = 3
BASE = dict(crop_height=128, crop_width=256, batch_size=2, train_iters=(1, 2, 3), max_disparity=64.0)
CAMPAIGN = dict(num_workers=1, crop_width=320, max_disparity=128.0)  # the lite campaign's settings since stretch 2
ROWS: dict[str, Row] = {
    "today": Row(
        "today: scenes made inline, 128x256, batch 2, iters 1/2/3",
        dict(num_workers=0),
        wide_transposed=False,
    ),
    "workers": Row("+ scenes made in 1 loader worker", dict(num_workers=1), wide_transposed=False),
    "wide": Row("+ 1x15 convs as transposed 15x1 (all of the above: the new step)", dict(num_workers=1)),
    "wide-active": Row("same, OpenMP threads spin (ACTIVE)", dict(num_workers=1), omp_wait_policy="ACTIVE"),
    "batch4": Row("new step, batch 4", dict(num_workers=1, batch_size=4)),
    "crop192": Row("new step, 192x384", dict(num_workers=1, crop_height=192, crop_width=384)),
    "iters246": Row("new step, iters 2/4/6", dict(num_workers=1, train_iters=(2, 4, 6))),
    "iters112": Row("new step, iters 1/1/2", dict(num_workers=1, train_iters=(1, 1, 2))),
    "campaign": Row("the campaign's step: 128x320, disparities to 128 px, 1 worker, ACTIVE", CAMPAIGN, "ACTIVE"),
    "campaign-bf16": Row(
        "same, bf16 autocast (only where the CPU has native bf16)", {**CAMPAIGN, "precision": "bf16"}, "ACTIVE"
    ),
    "campaign-iters246": Row(
        "the campaign's step, iters 2/4/6 (inference's counts)", {**CAMPAIGN, "train_iters": (2, 4, 6)}, "ACTIVE"
    ),
    "campaign-crop192": Row(
        "the campaign's step, 192x384", {**CAMPAIGN, "crop_height": 192, "crop_width": 384}, "ACTIVE"
    ),
}


GPU_RECIPE: dict[str, Any] = dict(
    crop_height=384,
    crop_width=512,
    batch_size=16,
    lr=2e-4,
    schedule="flat-decay",
    warmup_fraction=0.0,
    num_workers=0,
)
"""The GPU training step (bench/gpu_check's training stage) on top of the weights' own recipe:
384x512 crops, batch 16, lr 2e-4, scenes made on the device in the training process."""


@dataclass(frozen=True)
class ProbeRow:
    """One row of the GPU throughput probe: a name, what it changes, and its TrainConfig overrides."""

    name: str
    description: str
    overrides: dict[str, Any]


def probe_rows(batch_size: int, lr: float, factors: tuple[int, ...], options: bool, compiled: bool) -> list[ProbeRow]:
    """The probe's rows around a recipe of `batch_size` pairs per step at `lr`: the batch times each
    of `factors`, the lr scaled by the square root of the batch ratio (the usual rule for Adam);
    with `options`, at the third factor's batch (else the last's): plain (foreach) AdamW instead of
    the fused kernel, and channels-last; with `compiled`, at that batch: torch.compile, and
    torch.compile replaying CUDA graphs."""
    rows = [
        ProbeRow(
            f"batch{batch_size * factor}",
            f"batch {batch_size * factor}, lr {lr * math.sqrt(factor):.2e}",
            dict(batch_size=batch_size * factor, lr=lr * math.sqrt(factor)),
        )
        for factor in factors
    ]
    wide = rows[min(2, len(rows) - 1)].overrides
    if options:
        rows += [
            ProbeRow("foreach-adamw", f"batch {wide['batch_size']}, plain AdamW", {**wide, "fused_adamw": "off"}),
            ProbeRow("channels-last", f"batch {wide['batch_size']}, channels-last", {**wide, "channels_last": True}),
        ]
    if compiled:
        rows += [
            ProbeRow("compile", f"batch {wide['batch_size']}, torch.compile", {**wide, "compile": True}),
            ProbeRow(
                "cuda-graphs",
                f"batch {wide['batch_size']}, torch.compile reduce-overhead (CUDA graphs)",
                {**wide, "compile": True, "compile_mode": "reduce-overhead"},
            ),
        ]
    return rows


def measure_row(row: Row, steps: int, profile: bool) -> dict[str, Any]:
    """In this (child) process: a CPU row from the shipped lite weights (BASE plus its overrides)."""
    import torch

    from crestereo_pp.training.config import preset

    if not row.wide_transposed:
        import crestereo_pp.model.convolution

        crestereo_pp.model.convolution.WIDE_KERNEL = sys.maxsize  # every 1xk conv a plain nn.Conv2d, as before
    config = preset("pretrain", schedule="constant", **{**BASE, **row.overrides, "out_dir": "runs/bench-train-speed"})
    result = measure(config, ROOT / "model/weights/lite.pt", torch.device("cpu"), steps, profile=profile)
    return {**result, "threads": torch.get_num_threads()}


def measure(
    config: Any,
    weights: Path,
    device: Any,
    steps: int,
    max_seconds: float = math.inf,
    warmup_steps: int = 2,
    profile: bool = False,
) -> dict[str, Any]:
    """Time `steps` optimiser steps of the real `training.trainer.Trainer` (`config`, a TrainConfig,
    starting from `weights`) on `device`, after `warmup_steps` untimed ones (a compiled step compiles
    in the first); stops early once `max_seconds` have passed and MIN_TIMED_STEPS are timed.

    Returns seconds per step (median, the batch fetch included: data made on the critical path
    counts), of which `data_s` fetching the batch, pairs/s, the first step's seconds (compilation
    and autotuning show there), the steps timed, and the peak memory (GiB, CUDA only)."""
    import torch

    from crestereo_pp.training.data import TrainingData
    from crestereo_pp.training.distributed import DistributedContext
    from crestereo_pp.training.trainer import Trainer

    on_cuda = device.type == "cuda"

    def sync() -> None:
        if on_cuda:
            torch.cuda.synchronize(device)

    trainer = Trainer(config, DistributedContext(0, 1, 0), device, None, weights)
    trainer.network.train()
    if on_cuda:
        torch.cuda.reset_peak_memory_stats(device)
    batches = TrainingData(config, 0, device).batches(0)
    step_seconds: list[float] = []
    data_seconds: list[float] = []
    first_step_s = 0.0
    begin = time.perf_counter()
    for index in range(warmup_steps + steps):
        start = time.perf_counter()
        batch = next(batches)
        sync()
        fetched = time.perf_counter()
        if profile and index == warmup_steps + steps - 1:
            with torch.profiler.profile() as prof:
                trainer.train_step(batch)
            print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=20), file=sys.stderr)
        else:
            trainer.train_step(batch)
        sync()
        end = time.perf_counter()
        if index == 0:
            first_step_s = end - start
        if index >= warmup_steps:
            step_seconds.append(end - start)
            data_seconds.append(fetched - start)
            if len(step_seconds) >= MIN_TIMED_STEPS and end - begin > max_seconds:
                break
    step_s = statistics.median(step_seconds)
    return {
        "step_s": step_s,
        "data_s": statistics.median(data_seconds),
        "pairs_per_s": config.batch_size / step_s,
        "first_step_s": first_step_s,
        "timed_steps": len(step_seconds),
        "peak_gib": round(torch.cuda.max_memory_allocated(device) / 2**30, 2) if on_cuda else None,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=12, help="timed steps per row")
    parser.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS))
    parser.add_argument("--profile", choices=list(ROWS), help="print the operator profile of this row")
    parser.add_argument("--one", help=argparse.SUPPRESS)  # child mode: a row name
    args = parser.parse_args()
    if args.one:
        print(json.dumps(measure_row(ROWS[args.one], args.steps, args.one == args.profile)))
        return

    import torch

    print(
        f"torch {torch.__version__}, CPU capability {torch.backends.cpu.get_cpu_capability()}, {os.cpu_count()} CPUs\n"
    )
    print("| row | setting | s/step | pairs/s | vs today |")
    print("|---|---|---|---|---|")
    today = None
    for name in args.rows:
        row = ROWS[name]
        env = {**os.environ, "OMP_WAIT_POLICY": row.omp_wait_policy}
        command = [sys.executable, __file__, "--one", name, "--steps", str(args.steps)]
        if args.profile:
            command += ["--profile", args.profile]
        result = json.loads(subprocess.run(command, check=True, stdout=subprocess.PIPE, text=True, env=env).stdout)
        today = today or (result["pairs_per_s"] if name == "today" else None)
        ratio = f"{result['pairs_per_s'] / today:.2f}x" if today else "-"
        print(
            f"| {name} | {row.description} | {result['step_s']:.3f} | {result['pairs_per_s']:.2f} | {ratio} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
