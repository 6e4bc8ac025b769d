"""A prediction's maps as the command line and the service give them: metric depth where the
camera is known, in the rectified left frame or resampled into a raw pair's original left pixels."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .pointcloud import Calibration, DepthRange, metric_depth
from .rig import Rectifier

__all__ = ["OutputMaps", "output_maps"]


class OutputMaps(NamedTuple):
    """float32 HxW maps: disparity (px, +inf unknown), uncertainty in [0, 1], and depth (metres,
    +inf where there is none; None without a calibration)."""

    disparity: np.ndarray
    uncertainty: np.ndarray
    depth: np.ndarray | None


def output_maps(
    disparity: np.ndarray,
    uncertainty: np.ndarray,
    calibration: Calibration | None,
    limits: DepthRange,
    rectifier: Rectifier | None = None,
    original: bool = False,
) -> OutputMaps:
    """The maps of a prediction on a (rectified) pair, with depth where `calibration` is given;
    with `rectifier` and `original`, in the original left image's pixels (+inf disparity and
    depth, uncertainty 1, where a pixel has no rectified counterpart; depth along that camera's
    own axis)."""
    depth = None if calibration is None else metric_depth(disparity, calibration, limits)
    if rectifier is None or not original:
        return OutputMaps(disparity, uncertainty, depth)
    return OutputMaps(
        rectifier.to_original(disparity, np.inf),
        rectifier.to_original(uncertainty, 1.0),
        None if depth is None else rectifier.to_original_depth(depth),
    )
