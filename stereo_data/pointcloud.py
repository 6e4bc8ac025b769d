"""Point clouds from a disparity map: coloured points, written as binary PLY.

With a calibration (focal length f in px, baseline B in m, principal point (cx, cy) in px) the
points are metric, in the left camera's frame (x right, y down, z forward, metres):
Z = f B / d, X = (u - cx) Z / f, Y = (v - cy) Z / f. Without one they are image-space points
(u px, v px, d px). Pixels with no positive disparity, or whose uncertainty is above a chosen
threshold, are left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Calibration:
    """Rectified stereo rig: focal length (px), baseline (m), principal point (px; None = the
    image centre)."""

    focal_px: float
    baseline_m: float
    cx: float | None = None
    cy: float | None = None


def point_cloud(
    disparity: np.ndarray,
    left: np.ndarray,
    uncertainty: np.ndarray | None = None,
    calibration: Calibration | None = None,
    max_uncertainty: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(points float32 Nx3, colours uint8 Nx3 RGB) of the kept pixels, in row-major order.

    disparity: float HxW px; left: uint8 HxWx3 RGB (the colours); uncertainty: float HxW, needed
    with `max_uncertainty` (pixels above it are dropped).
    """
    height, width = disparity.shape
    if left.shape[:2] != (height, width):
        raise ValueError(f"left image {left.shape[:2]} and disparity {disparity.shape} differ in size")
    keep = np.isfinite(disparity) & (disparity > 0)
    if max_uncertainty is not None:
        if uncertainty is None:
            raise ValueError("max_uncertainty needs the uncertainty map")
        keep &= uncertainty <= max_uncertainty
    v, u = np.nonzero(keep)
    d = disparity[keep].astype(np.float64)
    if calibration is None:
        points = np.stack([u, v, d], axis=1)
    else:
        cx = (width - 1) / 2 if calibration.cx is None else calibration.cx
        cy = (height - 1) / 2 if calibration.cy is None else calibration.cy
        z = calibration.focal_px * calibration.baseline_m / d
        points = np.stack([(u - cx) * z / calibration.focal_px, (v - cy) * z / calibration.focal_px, z], axis=1)
    return points.astype(np.float32), np.ascontiguousarray(left[keep][:, :3]).astype(np.uint8)


def encode_ply(points: np.ndarray, colours: np.ndarray) -> bytes:
    """Binary little-endian PLY of float32 x, y, z and uint8 red, green, blue per vertex."""
    if points.ndim != 2 or points.shape[1] != 3 or colours.shape != points.shape:
        raise ValueError(f"expected Nx3 points and Nx3 colours, got {points.shape} and {colours.shape}")
    vertex = np.empty(
        len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    )
    vertex["x"], vertex["y"], vertex["z"] = points[:, 0], points[:, 1], points[:, 2]
    vertex["red"], vertex["green"], vertex["blue"] = colours[:, 0], colours[:, 1], colours[:, 2]
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment crestereo-pp point cloud\n"
        f"element vertex {len(points)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    return header.encode("ascii") + vertex.tobytes()
