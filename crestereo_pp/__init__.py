"""CREStereo++ and Lite-CREStereo++: stereo disparity and its uncertainty, as a library, a CLI and a service.

    from crestereo_pp import load_model
    predictor = load_model("lite")                  # the bundled weights
    prediction = predictor.predict(left_rgb, right_rgb)
    prediction.disparity, prediction.uncertainty    # float32 HxW: pixels of the left image, P(error > 2 px)

    from crestereo_pp import StereoClient           # the same from a running service, over HTTP

The project's folders are its subpackages (installed as `crestereo_pp.model`,
`crestereo_pp.inference`, `crestereo_pp.service`, ...; pyproject.toml maps them). The names below
are imported when first used, so that importing one subpackage (the client, a decoder process)
does not load torch.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .client import AsyncStereoClient, DisparityResult, DisparityStream, PointCloud, ServiceError, StereoClient
    from .inference import FrameStream, Prediction, StereoPredictor, TensorPrediction, load_model
    from .model import ModelConfig

# public name -> the subpackage that owns it
_OWNERS = {
    "load_model": "inference",
    "StereoPredictor": "inference",
    "Prediction": "inference",
    "TensorPrediction": "inference",
    "FrameStream": "inference",
    "ModelConfig": "model",
    "StereoClient": "client",
    "AsyncStereoClient": "client",
    "DisparityResult": "client",
    "DisparityStream": "client",
    "PointCloud": "client",
    "ServiceError": "client",
}

__all__ = [
    "AsyncStereoClient",
    "DisparityResult",
    "DisparityStream",
    "FrameStream",
    "ModelConfig",
    "PointCloud",
    "Prediction",
    "ServiceError",
    "StereoClient",
    "StereoPredictor",
    "TensorPrediction",
    "load_model",
]


def __getattr__(name: str) -> Any:
    """The public name `name`, imported from its subpackage on first use (PEP 562)."""
    if name not in _OWNERS:
        raise AttributeError(f"module 'crestereo_pp' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{_OWNERS[name]}", __name__), name)
    globals()[name] = value
    return value
