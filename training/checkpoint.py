"""Checkpoints: atomic save, load, and the random-number-generator states they carry.

A checkpoint is a dict saved with `torch.save`:
    "model": the network's state_dict (so a checkpoint loads as weights, see docs/CONTRACTS.md),
    "config": the ModelConfig as a dict, "model_name": "lite" | "full",
    "train_config": the TrainConfig as a dict, "optimizer", "scheduler": their state_dicts,
    "step": optimiser steps done, "rng": generator states, "training": cumulative metadata
    (see `training.trainer.TrainingHistory`).
Everything in it is a tensor or a builtin, so it loads with `torch.load(weights_only=True)`.
"""

from __future__ import annotations

import os
import random
from pathlib import Path
from typing import Any

import torch


def save_atomically(payload: dict[str, Any], path: Path) -> None:
    """torch.save `payload` to `path` through a temporary file and a rename, so that `path` is
    always either the previous complete file or the new complete file, never a partial one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    torch.save(payload, temporary)
    os.replace(temporary, path)


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """A checkpoint or weights file as a dict, tensors on the CPU."""
    payload = torch.load(Path(path), map_location="cpu", weights_only=True)
    if not isinstance(payload, dict) or "model" not in payload:
        raise ValueError(f"{path} is not a checkpoint or weights file: expected a dict with a 'model' state_dict")
    return payload


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
