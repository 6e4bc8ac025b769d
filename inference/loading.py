"""``load_model``: a predictor of the ``lite`` or ``full`` network with its weights, the bundled
ones (``model/weights/{name}.pt``) by default."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from crestereo_pp.model.config import ModelConfig
from crestereo_pp.model.network import CREStereoPP
from crestereo_pp.model.weights import (
    USABLE_BAD2,
    WEIGHTS_DIR,
    file_sha256,
    is_trained,
    network_from_weights,
    read_weights,
)

from .backend_choice import BackendChoice, PrecisionChoice, resolve_backend, resolve_precision
from .openvino_backend import MAX_COMPILED_BYTES
from .options import Iterations
from .predictor import StereoPredictor
from .uncertainty_calibration import UncertaintyCalibration


def load_model(
    name: str = "lite",
    weights: str | Path | None = None,
    device: str | torch.device = "cpu",
    *,
    backend: BackendChoice = "auto",
    precision: PrecisionChoice = "auto",
    cuda_graphs: bool = True,
    cache_dir: str | Path | None = None,
    compiled_bytes: int = MAX_COMPILED_BYTES,
    prepare_iters: Sequence[Iterations] = (),
) -> StereoPredictor:
    """Build the ``name`` network (``lite`` | ``full``) and load its weights.

    ``weights``: a weights file or training checkpoint (a dict with ``"model"`` = state_dict and
    ``"config"``); None loads the bundled ``model/weights/{name}.pt`` if present, else the network is
    randomly initialised (seed 0, so every process gets the same one) with a warning.
    ``backend`` and ``precision``: see ``resolve_backend`` and ``resolve_precision``; the
    predictor's ``backend`` and ``precision`` say what was picked. ``cuda_graphs``, ``cache_dir``
    and ``compiled_bytes``: see ``StereoPredictor``. ``prepare_iters``: iteration settings whose fast
    paths, for cold and warm starts, are made ready in the background at once (``prepare`` with
    ``wait=False``: OpenVINO reads their graphs from the cache or exports them).
    """
    config = ModelConfig.preset(name)  # an unknown name: ValueError before anything else is said
    device = torch.device(device)
    chosen = resolve_backend(backend, device)
    options: dict[str, Any] = {
        "backend": chosen,
        "precision": resolve_precision(precision, chosen),
        "cuda_graphs": cuda_graphs,
        "cache_dir": None if cache_dir is None else Path(cache_dir),
        "compiled_bytes": compiled_bytes,
    }
    path = Path(weights) if weights is not None else WEIGHTS_DIR / f"{name}.pt"
    if weights is None and not path.is_file():
        warnings.warn(
            f"no weights at {path}: the {name!r} model is randomly initialised and its predictions are meaningless",
            RuntimeWarning,
            stacklevel=2,
        )
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(0)
            network = CREStereoPP(config)
        predictor = StereoPredictor(network, name, None, device, **options)
    else:
        payload = read_weights(path, name)
        if not is_trained(payload.get("training")):
            warnings.warn(
                f"the {name!r} weights at {path} are untrained (no validation on real pairs reaching "
                f"{USABLE_BAD2:g} % bad-2): their maps are not usable",
                RuntimeWarning,
                stacklevel=2,
            )
        calibration = payload.get("calibration")
        predictor = StereoPredictor(
            network_from_weights(payload, name),
            name,
            file_sha256(path),
            device,
            UncertaintyCalibration.from_dict(calibration) if calibration is not None else None,
            payload.get("training"),
            **options,
        )
    for iters in prepare_iters:
        for warm_start in (False, True):
            predictor.prepare(iters, warm_start=warm_start, wait=False)
    return predictor
