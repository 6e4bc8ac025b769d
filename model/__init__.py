"""CREStereo++ and Lite-CREStereo++ in plain PyTorch.

Disparity is positive everywhere, in pixels of the left image (the right match is at x - d).

    from crestereo_pp.model import load_model
    predictor = load_model("lite")                  # bundled weights if present
    disparity, uncertainty = predictor.predict(left_rgb, right_rgb)
"""

from .config import ModelConfig
from .inference import FrameStream, Prediction, StereoPredictor, TensorPrediction, load_model
from .loss import matching_loss, sequence_loss
from .network import CREStereoPP, NetworkOutput, padded_size
from .options import (
    TWO_PASS_CHOICES,
    InferenceOptions,
    Iterations,
    StageCounts,
    TwoPass,
    WarmStart,
    parse_iterations,
    parse_two_pass,
)

__all__ = [
    "TWO_PASS_CHOICES",
    "CREStereoPP",
    "FrameStream",
    "InferenceOptions",
    "Iterations",
    "ModelConfig",
    "NetworkOutput",
    "Prediction",
    "StageCounts",
    "StereoPredictor",
    "TensorPrediction",
    "TwoPass",
    "WarmStart",
    "load_model",
    "matching_loss",
    "padded_size",
    "parse_iterations",
    "parse_two_pass",
    "sequence_loss",
]
