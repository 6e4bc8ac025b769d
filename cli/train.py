"""`crestereo-pp train`: a preset plus any TrainConfig field as an option."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from crestereo_pp.model.weights import read_weights
from crestereo_pp.training.config import PRESETS, TrainConfig, preset
from crestereo_pp.training.distributed import DistributedContext
from crestereo_pp.training.trainer import train

from .dataclass_args import add_dataclass_options, given_options


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Train CREStereo++ / Lite-CREStereo++. Start from a preset (the paper's two stages), "
        "override any field below, or continue a checkpoint exactly with --resume (its config, "
        "plus the options given here). Writes checkpoint.pt, log.csv and loss_curve.png to "
        "--out-dir. Several GPUs or nodes: torchrun --nproc-per-node N -m cli.main train ..."
    )
    parser.add_argument("--preset", choices=sorted(PRESETS), help="starting config [pretrain]")
    start = parser.add_mutually_exclusive_group()
    start.add_argument("--resume", type=Path, metavar="CHECKPOINT", help="continue this checkpoint exactly")
    start.add_argument(
        "--init-weights",
        type=Path,
        metavar="WEIGHTS",
        help="start from these weights with a fresh optimiser, at step 0",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_dataclass_options(parser.add_argument_group("training config"), TrainConfig)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    overrides = given_options(args, TrainConfig)
    if args.resume is not None:
        if args.preset is not None:
            raise SystemExit(
                "crestereo-pp train: --preset cannot be combined with --resume (the checkpoint has its config)"
            )
        config = replace(TrainConfig.from_dict(read_weights(args.resume)["train_config"]), **overrides)
    else:
        config = preset(args.preset or "pretrain", **overrides)
    result = train(config, resume=args.resume, init_weights=args.init_weights, progress=not args.no_progress)
    if DistributedContext.from_environment().is_main:
        reason = "time budget reached" if result.out_of_time else "max_steps reached"
        print(f"stopped at step {result.step} ({reason}); checkpoint: {result.checkpoint}")
    return 0
