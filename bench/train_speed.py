"""Pairs per second of a lite training step on this machine, for the settings worth comparing.

    python bench/train_speed.py [--steps 12] [--rows today workers ...] [--profile ROW]

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
import os
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run from a checkout without installing


@dataclass(frozen=True)
class Row:
    """One setting: TrainConfig overrides, and the process-level switches."""

    description: str
    overrides: dict[str, Any] = field(default_factory=dict)
    omp_wait_policy: str = "PASSIVE"
    wide_transposed: bool = True  # 1x15 gate convs computed as transposed 15x1 (model.update)


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


def measure(row: Row, steps: int, profile: bool) -> dict[str, Any]:
    """In this (child) process: seconds per step of `row`."""
    import torch

    from training.config import preset
    from training.data import TrainingData
    from training.distributed import DistributedContext
    from training.trainer import Trainer

    if not row.wide_transposed:
        import model.convolution

        model.convolution.WIDE_KERNEL = sys.maxsize  # every 1xk conv a plain nn.Conv2d, as before
    overrides = {**BASE, **row.overrides, "max_steps": steps + 2, "out_dir": "runs/bench-train-speed"}
    config = preset("pretrain", schedule="constant", **overrides)
    device = torch.device("cpu")
    trainer = Trainer(config, DistributedContext(0, 1, 0), device, None, ROOT / "model/weights/lite.pt")
    trainer.network.train()
    batches = TrainingData(config, 0, device).batches(0)
    seconds = []
    for index in range(steps + 2):
        start = time.perf_counter()
        batch = next(batches)
        if profile and index == steps + 1:
            with torch.profiler.profile() as prof:
                trainer.train_step(batch)
            print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=20), file=sys.stderr)
        else:
            trainer.train_step(batch)
        seconds.append(time.perf_counter() - start)
    step_s = statistics.median(seconds[2:])
    return {"step_s": step_s, "pairs_per_s": config.batch_size / step_s, "threads": torch.get_num_threads()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=12, help="timed steps per row")
    parser.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS))
    parser.add_argument("--profile", choices=list(ROWS), help="print the operator profile of this row")
    parser.add_argument("--one", help=argparse.SUPPRESS)  # child mode: a row name
    args = parser.parse_args()
    if args.one:
        print(json.dumps(measure(ROWS[args.one], args.steps, args.one == args.profile)))
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
