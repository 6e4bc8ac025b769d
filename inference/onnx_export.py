"""ONNX export of a predictor: the network, its padding and its uncertainty calibration in one
graph of a fixed input size, for ONNX Runtime or other ONNX runtimes."""

from __future__ import annotations

import warnings
from pathlib import Path

import torch
from torch import Tensor, nn

from .onnx_optimize import optimize_onnx
from .options import Iterations
from .predictor import StereoPredictor


class ExportedGraph(nn.Module):
    """What the ONNX file computes: ``predict`` on a batch of image tensors.

    forward(left, right): (B, 3, H, W) float32 RGB in [0, 255] -> disparity (B, 1, H, W) float32,
    positive, pixels of the left image; uncertainty (B, 1, H, W) in [0, 1], calibrated as
    ``predict`` serves it when the weights carry a calibration, else the paper's U.
    """

    def __init__(self, predictor: StereoPredictor, iters: Iterations = None) -> None:
        super().__init__()
        self.predictor = predictor
        self.network = predictor.network  # registered, so the weights are the graph's initialisers
        self.counts = predictor.iterations(iters)

    def forward(self, left: Tensor, right: Tensor) -> tuple[Tensor, Tensor]:
        disparity, uncertainty = self.predictor.forward_padded(left, right, self.counts, None)
        return disparity, self.predictor.served_uncertainty(uncertainty, disparity, left, right)


def export_onnx(
    predictor: StereoPredictor, path: Path, height: int, width: int, batch: int = 1, iters: Iterations = None
) -> None:
    """Write `predictor` as an ONNX model (opset 18) taking inputs "left" and "right" of exactly
    (batch, 3, height, width) and giving "disparity" and "uncertainty" (see ExportedGraph).
    Any height and width: the graph pads to the network's input multiple itself."""
    if height < 1 or width < 1 or batch < 1:
        raise ValueError(f"need a positive batch and size, got batch {batch}, {height}x{width}")
    graph = ExportedGraph(predictor, iters).eval()
    # two distinct tensors: the exporter would take one tensor passed twice for one input
    left, right = torch.full((2, batch, 3, height, width), 128.0, device=predictor.device).unbind(0)
    path.parent.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the exporter's own deprecation chatter, not ours
        program = torch.onnx.export(
            graph,
            (left, right),
            dynamo=True,
            opset_version=18,
            input_names=["left", "right"],
            output_names=["disparity", "uncertainty"],
            verbose=False,
            optimize=False,  # optimize_onnx: the same passes, faster
        )
    assert program is not None  # dynamo=True always returns the program
    optimize_onnx(program.model)
    program.save(str(path))
