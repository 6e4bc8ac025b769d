"""A prediction's outputs as the command line writes them and the service answers them: metric
depth where the camera is known, the maps in the rectified left frame or resampled into a raw
pair's original left pixels, the coloured disparity of the pictures and the point cloud."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .pointcloud import IMAGE_FRAME, METRIC_FRAME, DepthRange, FocalBaseline, encode_ply, metric_depth, point_cloud
from .rig import Rectifier
from .visualize import scale_range

__all__ = ["OutputMaps", "OutputOptions", "PredictionOutputs"]


class OutputMaps(NamedTuple):
    """float32 HxW maps: disparity (px, +inf unknown), uncertainty in [0, 1], and depth (metres,
    +inf where there is none; None without a calibration)."""

    disparity: np.ndarray
    uncertainty: np.ndarray
    depth: np.ndarray | None


@dataclass(frozen=True)
class OutputOptions:
    """How a prediction becomes its outputs.

    focal_baseline: the (rectified) left camera: depth and metric points (None: neither); limits:
    the disparities and depths kept (`DepthRange`); rectifier and original: a raw pair's rectifier,
    and whether the maps go back into its original left image's pixels; color_min, color_max: the
    ends of the disparity colour scale (None: the map's robust range); max_uncertainty: points
    above it are dropped from the point cloud.
    """

    focal_baseline: FocalBaseline | None
    limits: DepthRange
    rectifier: Rectifier | None = None
    original: bool = False
    color_min: float | None = None
    color_max: float | None = None
    max_uncertainty: float | None = None


class PredictionOutputs:
    """The outputs of one prediction on a (rectified) pair: its maps at once (`maps`), the coloured
    disparity and the point cloud when asked for.

    disparity, uncertainty: the network's float32 HxW maps (px of `left`; [0, 1]); left: the uint8
    HxWx3 RGB left image the network saw (the point cloud's colours).
    """

    def __init__(
        self, disparity: np.ndarray, uncertainty: np.ndarray, left: np.ndarray, options: OutputOptions
    ) -> None:
        self.disparity, self.uncertainty, self.left, self.options = disparity, uncertainty, left, options
        self.maps = _output_maps(disparity, uncertainty, options)

    def colored_disparity(self) -> tuple[np.ndarray, tuple[float, float]]:
        """The output disparity as the pictures colour it (a pixel without a rectified counterpart
        at the bottom of the scale) and its colour scale in px (`stereo_data.visualize.scale_range`)."""
        shown = np.where(np.isfinite(self.maps.disparity), self.maps.disparity, 0.0)
        return shown, scale_range(shown, self.options.color_min, self.options.color_max)

    def ply(self, comments: Sequence[str] = ()) -> bytes:
        """The binary PLY point cloud of the pair the network saw, coloured by its left image:
        metric in the (rectified) left camera's frame where the camera is known, else image-space
        points (`stereo_data.pointcloud`); `comments` are added to its header."""
        options = self.options
        points, colors = point_cloud(
            self.disparity, self.left, self.uncertainty, options.focal_baseline, options.max_uncertainty, options.limits
        )
        return encode_ply(points, colors, IMAGE_FRAME if options.focal_baseline is None else METRIC_FRAME, comments)


def _output_maps(disparity: np.ndarray, uncertainty: np.ndarray, options: OutputOptions) -> OutputMaps:
    """The maps of a prediction, with depth where the camera is known; with a rectifier and
    `original`, in the original left image's pixels (+inf disparity and depth, uncertainty 1, where
    a pixel has no rectified counterpart; depth along that camera's own axis)."""
    depth = None if options.focal_baseline is None else metric_depth(disparity, options.focal_baseline, options.limits)
    rectifier = options.rectifier
    if rectifier is None or not options.original:
        return OutputMaps(disparity, uncertainty, depth)
    return OutputMaps(
        rectifier.to_original(disparity, np.inf),
        rectifier.to_original(uncertainty, 1.0),
        None if depth is None else rectifier.to_original_depth(depth),
    )
