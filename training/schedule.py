"""Learning-rate schedules: linear warm-up, then cosine (one-cycle), linear or no decay."""

from __future__ import annotations

import math

import torch

from .config import Schedule


def learning_rate_factor(step: int, total_steps: int, schedule: Schedule, warmup_fraction: float) -> float:
    """Multiplier of the peak lr for optimiser step `step` (0-based) of `total_steps`.

    The first ceil(warmup_fraction * total_steps) steps ramp linearly up to 1; then "one-cycle"
    anneals to 0 along a half cosine, "linear" decays linearly to 0 and "constant" stays at 1.
    """
    warmup_steps = math.ceil(warmup_fraction * total_steps)
    if step < warmup_steps:
        return (step + 1) / warmup_steps
    if schedule == "constant":
        return 1.0
    progress = min(1.0, (step - warmup_steps) / max(1, total_steps - warmup_steps))
    if schedule == "linear":
        return 1.0 - progress
    if schedule == "one-cycle":
        return 0.5 * (1.0 + math.cos(math.pi * progress))
    raise ValueError(f"unknown schedule {schedule!r}")


def build_scheduler(
    optimizer: torch.optim.Optimizer, total_steps: int, schedule: Schedule, warmup_fraction: float
) -> torch.optim.lr_scheduler.LambdaLR:
    """A LambdaLR applying `learning_rate_factor`; its state_dict holds only the step count, so a
    resumed run with a different `total_steps` follows the new horizon from where it stands."""

    def factor(step: int) -> float:
        return learning_rate_factor(step, total_steps, schedule, warmup_fraction)

    return torch.optim.lr_scheduler.LambdaLR(optimizer, factor)
