"""The weights file: the one reader and writer of the format (docs/CONTRACTS.md).

A weights file is a dict saved with `torch.save`, every value a tensor or a builtin, so it loads
with `torch.load(weights_only=True)`:
    "model": the network's state_dict (float32, or float16 for a `--fp16` export),
    "config": the ModelConfig as a dict (absent in old files: the preset of the name is used),
    "model_name": "lite" | "full",
    "calibration": the fitted uncertainty calibration (model.calibration), when present,
    "training": the cumulative training record, "train_config", "step", "dtype": metadata.
A training checkpoint is a weights file with more keys ("optimizer", "scheduler", "rng", and
"train_model" when "model" is a moving average of the trained weights: those raw weights, which
a resumed run continues from), so it loads as weights directly.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any

import torch

from .config import ModelConfig
from .network import CREStereoPP

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


def read_weights(path: str | Path) -> dict[str, Any]:
    """The weights file (or checkpoint) at `path` as a dict, tensors on the CPU.

    Raises FileNotFoundError when there is no file, ValueError when it is not a weights file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"weights file not found: {path}")
    payload = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(payload, dict) or "model" not in payload:
        raise ValueError(f"{path} is not a weights file or checkpoint: expected a dict with a 'model' state_dict")
    return payload


def write_weights(payload: dict[str, Any], path: str | Path) -> None:
    """torch.save `payload` to `path` through a temporary file and a rename, so that `path` is
    always either the previous complete file or the new complete file, never a partial one."""
    if "model" not in payload:
        raise ValueError("a weights payload needs the 'model' state_dict")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    torch.save(payload, temporary)
    os.replace(temporary, path)


def model_config_of(payload: dict[str, Any], name: str) -> ModelConfig:
    """The network config stored in `payload`, or the `name` preset for files that have none."""
    if "config" in payload:
        return ModelConfig.from_dict(dict(payload["config"]))
    return ModelConfig.preset(name)


def network_from_weights(payload: dict[str, Any], name: str) -> CREStereoPP:
    """A float32 CREStereoPP built from `payload`'s config with its state_dict loaded."""
    network = CREStereoPP(model_config_of(payload, name))
    load_state(network, payload)
    return network


def load_state(network: CREStereoPP, payload: dict[str, Any], key: str = "model") -> None:
    """Load `payload[key]` (a state_dict: "model", or a checkpoint's "train_model") into `network`,
    float16 tensors cast back to float32."""
    state = payload[key]
    network.load_state_dict({name: t.float() if t.is_floating_point() else t for name, t in state.items()})


def file_sha256(path: Path) -> str:
    """Hex sha256 of the file at `path` (the served weights' identity)."""
    digest = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
