"""The runtime of CREStereo++ and Lite-CREStereo++: the network (``crestereo_pp.model``) ready for
inference on images of any size, on torch, CUDA graphs or OpenVINO.

Disparity is positive everywhere, in pixels of the left image (the right match is at x - d).

    from crestereo_pp.inference import load_model
    predictor = load_model("lite")                  # bundled weights if present
    disparity, uncertainty = predictor.predict(left_rgb, right_rgb)
    offset = measure_row_offset(left_rgb, right_rgb)  # how far the right rows lie off the left's
"""

from .batching import PairMaps
from .loading import load_model
from .options import (
    NETWORK_ONLY,
    TWO_PASS_CHOICES,
    InferenceOptions,
    Iterations,
    StageCounts,
    TwoPass,
    parse_iterations,
    parse_two_pass,
)
from .prediction import Prediction, TensorPrediction
from .predictor import StereoPredictor
from .row_alignment import RowOffset, measure_row_offset
from .warm_start import FrameStream, WarmStart

__all__ = [
    "NETWORK_ONLY",
    "TWO_PASS_CHOICES",
    "FrameStream",
    "InferenceOptions",
    "PairMaps",
    "Iterations",
    "Prediction",
    "RowOffset",
    "StageCounts",
    "StereoPredictor",
    "TensorPrediction",
    "TwoPass",
    "WarmStart",
    "load_model",
    "measure_row_offset",
    "parse_iterations",
    "parse_two_pass",
]
