"""Learning-rate schedules: linear warm-up, then cosine (one-cycle), linear, no decay, or flat with a
short linear decay at the end (flat-decay)."""

from __future__ import annotations

import math

import torch

from .config import Schedule


def learning_rate_factor(
    step: int, total_steps: int, schedule: Schedule, warmup_fraction: float, decay_steps: int = 0
) -> float:
    """Multiplier of the peak lr for optimiser step `step` (0-based) of `total_steps`.

    The first ceil(warmup_fraction * total_steps) steps ramp linearly up to 1; then "one-cycle"
    anneals to 0 along a half cosine, "linear" decays linearly to 0, "constant" stays at 1 and
    "flat-decay" stays at 1 until the last `decay_steps` steps, over which it decays linearly to 0
    (a long run at the peak that can stop at a low-noise point: resume with a later total).
    """
    warmup_steps = math.ceil(warmup_fraction * total_steps)
    if step < warmup_steps:
        return (step + 1) / warmup_steps
    if schedule == "constant":
        return 1.0
    if schedule == "flat-decay":
        return min(1.0, max(0.0, (total_steps - step) / max(1, decay_steps)))
    progress = min(1.0, (step - warmup_steps) / max(1, total_steps - warmup_steps))
    if schedule == "linear":
        return 1.0 - progress
    if schedule == "one-cycle":
        return 0.5 * (1.0 + math.cos(math.pi * progress))
    raise ValueError(f"unknown schedule {schedule!r}")


def build_scheduler(
    optimizer: torch.optim.Optimizer,
    total_steps: int,
    schedule: Schedule,
    warmup_fraction: float,
    decay_steps: int = 0,
) -> torch.optim.lr_scheduler.LambdaLR:
    """A LambdaLR applying `learning_rate_factor`; its state_dict holds only the step count, so a
    resumed run with a different `total_steps` follows the new horizon from where it stands."""
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: 1.0)
    set_horizon(scheduler, total_steps, schedule, warmup_fraction, decay_steps)
    return scheduler


def set_horizon(
    scheduler: torch.optim.lr_scheduler.LambdaLR,
    total_steps: int,
    schedule: Schedule,
    warmup_fraction: float,
    decay_steps: int = 0,
) -> None:
    """Make `scheduler` follow `learning_rate_factor` over `total_steps` from the step it stands at:
    the optimiser's lr is set at once to the new schedule's value for that step."""

    def factor(step: int) -> float:
        return learning_rate_factor(step, total_steps, schedule, warmup_fraction, decay_steps)

    scheduler.lr_lambdas = [factor] * len(scheduler.optimizer.param_groups)
    for group, base_lr in zip(scheduler.optimizer.param_groups, scheduler.base_lrs, strict=True):
        group["lr"] = base_lr * factor(scheduler.last_epoch)
