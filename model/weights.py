"""The weights file: the one reader and writer of the format (docs/CONTRACTS.md), and the one
spelling of its keys (`WeightsFile`).

A weights file is a dict saved with `torch.save`, every value a tensor or a builtin, so it loads
with `torch.load(weights_only=True)`. A training checkpoint is a weights file with more keys
(`CHECKPOINT_KEYS`), so it loads as weights directly.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any, NotRequired, TypedDict, cast

import torch
from torch import Tensor

from .config import ModelConfig
from .network import CREStereoPP


class WeightsFile(TypedDict):
    """What a weights file (or checkpoint) holds; only "model" is always there.

    model: the network's state_dict (float32, or float16 for a `--fp16` export).
    config: the ModelConfig as a dict (absent in old files: the preset of the name is used).
    model_name: "lite" | "full".
    calibration: the fitted uncertainty calibration (inference.uncertainty_calibration), when present.
    training: the cumulative training record (training.history); train_config: the TrainConfig
        as a dict; step: optimiser steps done; dtype: "float32" | "float16".
    Checkpoints only (CHECKPOINT_KEYS): train_model: the raw trained weights when "model" is
    their moving average (a resumed run continues them); optimizer, scheduler: state_dicts;
    rng: the random generators' states (training.checkpoint).
    """

    model: dict[str, Tensor]
    config: NotRequired[dict[str, Any]]
    model_name: NotRequired[str]
    calibration: NotRequired[dict[str, Any]]
    training: NotRequired[dict[str, Any]]
    train_config: NotRequired[dict[str, Any]]
    step: NotRequired[int]
    dtype: NotRequired[str]
    train_model: NotRequired[dict[str, Tensor]]
    optimizer: NotRequired[dict[str, Any]]
    scheduler: NotRequired[dict[str, Any]]
    rng: NotRequired[dict[str, Any]]


CHECKPOINT_KEYS = ("train_model", "optimizer", "scheduler", "rng")
"""The keys only a training checkpoint has (what `weights_of` drops)."""


def weights_of(checkpoint: WeightsFile, half: bool = False) -> WeightsFile:
    """The weights file of a checkpoint (or of another weights file): every key but the training
    state (CHECKPOINT_KEYS); with `half`, floating-point tensors stored as float16 (half the size;
    `load_state` casts them back to float32) and "dtype" saying so."""
    payload: dict[str, Any] = {key: value for key, value in checkpoint.items() if key not in CHECKPOINT_KEYS}
    if half:
        payload["model"] = {name: t.half() if t.is_floating_point() else t for name, t in checkpoint["model"].items()}
    payload["dtype"] = "float16" if half else "float32"
    return cast(WeightsFile, payload)  # the checkpoint's own keys


WEIGHTS_DIR = Path(__file__).parent / "weights"
"""Bundled weights: ``WEIGHTS_DIR / f"{name}.pt"``."""


USABLE_BAD2 = 50.0
"""Weights count as trained once a validation on real pairs recorded in them has a mean bad-2 (%)
at most this: beyond it the maps are mostly wrong."""


def is_trained(training: dict[str, Any] | None) -> bool:
    """Whether weights with this training record (the ``"training"`` entry of a weights file) are
    trained: their last recorded validation on real pairs has bad-2 at most USABLE_BAD2 %. Weights
    never validated, or without a record, count as untrained."""
    runs = (training or {}).get("runs") or []
    validations = [run["validation"] for run in runs if run.get("validation")]
    return bool(validations) and float(validations[-1]["bad2"]) <= USABLE_BAD2


def read_weights(path: str | Path, model: str | None = None) -> WeightsFile:
    """The weights file (or checkpoint) at `path` as a dict, tensors on the CPU.

    Raises FileNotFoundError when there is no file, ValueError when it is not a weights file, or
    when `model` is given and the file holds another model's weights (files that name no model
    pass: they are read as `model`'s)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"weights file not found: {path}")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch's unpickler meets other bytes with whatever they trip (KeyError, ...)
        if isinstance(error, RuntimeError):
            reason = str(error).split(". ")[0]  # a zip archive cut short or damaged: torch's first sentence
        elif isinstance(error, EOFError):
            reason = "empty"
        else:
            reason = "not a file torch saved, or one holding more than tensors and plain values"
        raise ValueError(f"{path} is not a weights file or checkpoint: torch cannot read it ({reason})") from None
    if not isinstance(payload, dict) or "model" not in payload:
        raise ValueError(f"{path} is not a weights file or checkpoint: expected a dict with a 'model' state_dict")
    held = payload.get("model_name", model)
    if model is not None and held != model:
        raise ValueError(f"{path} holds {held!r} weights, not {model!r}: load them as {held!r}")
    return cast(WeightsFile, payload)  # the file's own keys, checked where they are read


def write_weights(payload: WeightsFile, path: str | Path) -> None:
    """torch.save `payload` to `path` through a temporary file and a rename, so that `path` is
    always either the previous complete file or the new complete file, never a partial one."""
    if "model" not in payload:
        raise ValueError("a weights payload needs the 'model' state_dict")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    torch.save(payload, temporary)
    os.replace(temporary, path)


def model_config_of(payload: WeightsFile, name: str) -> ModelConfig:
    """The network config stored in `payload`, or the `name` preset for files that have none."""
    if "config" in payload:
        return ModelConfig.from_dict(dict(payload["config"]))
    return ModelConfig.preset(name)


def network_from_weights(payload: WeightsFile, name: str) -> CREStereoPP:
    """A float32 CREStereoPP built from `payload`'s config with its state_dict loaded."""
    network = CREStereoPP(model_config_of(payload, name))
    load_state(network, payload["model"])
    return network


def load_state(network: CREStereoPP, state: dict[str, Tensor]) -> None:
    """Load a state_dict (a weights file's "model", or a checkpoint's "train_model") into
    `network`, float16 tensors cast back to float32."""
    network.load_state_dict({name: t.float() if t.is_floating_point() else t for name, t in state.items()})


def file_sha256(path: Path) -> str:
    """Hex sha256 of the file at `path` (the served weights' identity)."""
    digest = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
