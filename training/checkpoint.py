"""The random-number-generator states a training checkpoint carries.

A checkpoint is a weights file (read and written by `model.weights`) with these keys besides the
weights': "train_config": the TrainConfig as a dict, "optimizer", "scheduler": their
state_dicts, "step": optimiser steps done, "rng": the states below, "training": cumulative
metadata (see `training.history.TrainingHistory`).
"""

from __future__ import annotations

import random
from typing import Any

import torch


def rng_state() -> dict[str, Any]:
    """States of Python's, torch's CPU and (where present) every CUDA device's generators."""
    state: dict[str, Any] = {"python": random.getstate(), "torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def restore_rng_state(state: dict[str, Any]) -> None:
    """Inverse of `rng_state` (CUDA states are restored only where CUDA is available)."""
    random.setstate(state["python"])
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
