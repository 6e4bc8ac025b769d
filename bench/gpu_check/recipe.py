"""What the probe and train stages train: each model's weights to start from and its training step."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .plans import REPO, Plan

if TYPE_CHECKING:
    from crestereo_pp.model.config import ModelName

RESUME_DIR = REPO / "training" / "resume"
"""The stable branch of each model's last GPU run (its stable.pt), committed beside the shipped
weights so that the next run goes on at the peak lr (warmup-stable-decay)."""


def weights_for(model: str, args: argparse.Namespace) -> Path:
    """The weights file a stage trains `model` from: --weights for the --model, else the stable
    branch of its last GPU run (training/resume/MODEL.pt, where one was kept), else the shipped file."""
    from crestereo_pp.model.weights import WEIGHTS_DIR

    if args.weights is not None and model == args.model:
        return Path(args.weights)
    stable = RESUME_DIR / f"{model}.pt"
    return stable if stable.is_file() else WEIGHTS_DIR / f"{model}.pt"


def recipe_of(model: ModelName, plan: Plan, args: argparse.Namespace) -> Any:
    """The TrainConfig of a stage's training step for `model`: the data recipe of the shipped lite
    weights (scenes, disparities, photometry: what the campaign settled on) with the model's own
    iterations, then the plan's step (plan.train), --train-compile and --train-set."""
    from crestereo_pp.model.weights import WEIGHTS_DIR, read_weights
    from crestereo_pp.training.config import TrainConfig

    return replace(
        TrainConfig.from_dict(read_weights(WEIGHTS_DIR / "lite.pt")["train_config"]),
        **{"train_iters": None, **plan.train, "compile": args.train_compile, **dict(args.train_set)},
        model=model,
        device=plan.device,
    )
