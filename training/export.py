"""Export a training checkpoint as a weights file (docs/CONTRACTS.md format), optionally fp16."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from model.weights import read_weights, write_weights


def export_weights(checkpoint: Path, output: Path, half: bool = False) -> dict[str, Any]:
    """Write `output` = {"model", "config", "model_name", "train_config", "step", "training",
    "calibration"}
    from a checkpoint, dropping the optimiser, scheduler and RNG states.

    half: store floating-point tensors as float16 (half the size; `model.weights.load_state`
    casts them back to float32). Returns the written payload.
    """
    source = read_weights(checkpoint)
    state = source["model"]
    if half:
        state = {name: t.half() if t.is_floating_point() else t for name, t in state.items()}
    payload = {
        "model": state,
        "config": source["config"],
        "model_name": source.get("model_name"),
        "train_config": source.get("train_config"),
        "step": source.get("step"),
        "training": source.get("training"),
        "calibration": source.get("calibration"),  # fitted for these weights (model.calibration)
        "dtype": "float16" if half else "float32",
    }
    write_weights(payload, output)
    return payload
