"""Metric depth and point clouds from a disparity map; point clouds written (and read back) as binary PLY.

With a focal length and baseline (`FocalBaseline`: focal length f in px, baseline B in m, principal
point (cx, cy) in px) the points are metric, in the left camera's frame (x right, y down, z forward, metres):
Z = f B / d, X = (u - cx) Z / f, Y = (v - cy) Z / f. Without one they are image-space points
(u px, v px, d px). Disparities at or below a minimum (`MIN_DISPARITY` px by default: depth there
is beyond what the matching can resolve, out to infinity at 0), metric points beyond a maximum
depth, and pixels whose uncertainty is above a chosen threshold are left out.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

MIN_DISPARITY = 1.0
"""Default smallest disparity (px) that gives a depth or a point: below a pixel the matching's own
error (about 2 px) exceeds the disparity, and Z = f B / d runs off to kilometres (KITTI: 389 m at
1 px)."""


@dataclass(frozen=True)
class FocalBaseline:
    """What turns disparity into depth: a rectified stereo camera's focal length (px), baseline (m)
    and principal point (px; None = the image centre)."""

    focal_px: float
    baseline_m: float
    cx: float | None = None
    cy: float | None = None


@dataclass(frozen=True)
class DepthRange:
    """Which pixels give a depth or a point: disparity above `min_disparity` px and, for metric
    depth, Z at most `max_depth_m` metres (None: no limit)."""

    min_disparity: float = MIN_DISPARITY
    max_depth_m: float | None = None

    def __post_init__(self) -> None:
        if not self.min_disparity >= 0:
            raise ValueError(f"min_disparity must be >= 0 px, got {self.min_disparity}")
        if self.max_depth_m is not None and not self.max_depth_m > 0:
            raise ValueError(f"max_depth_m must be positive, got {self.max_depth_m}")


def metric_depth(disparity: np.ndarray, focal_baseline: FocalBaseline, limits: DepthRange = DepthRange()) -> np.ndarray:
    """Depth Z = f B / d in metres, float32 HxW, of a disparity map (float HxW, px); +inf where the
    pixel gives no depth (disparity not finite or at most `limits.min_disparity`, or Z beyond
    `limits.max_depth_m`)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.float32(focal_baseline.focal_px * focal_baseline.baseline_m) / disparity
    keep = np.isfinite(disparity) & (disparity > limits.min_disparity)
    if limits.max_depth_m is not None:
        keep &= depth <= limits.max_depth_m
    return np.where(keep, depth, np.inf).astype(np.float32)


def point_cloud(
    disparity: np.ndarray,
    left: np.ndarray,
    uncertainty: np.ndarray | None = None,
    focal_baseline: FocalBaseline | None = None,
    max_uncertainty: float | None = None,
    limits: DepthRange = DepthRange(),
) -> tuple[np.ndarray, np.ndarray]:
    """(points float32 Nx3, colours uint8 Nx3 RGB) of the kept pixels, in row-major order.

    disparity: float HxW px; left: uint8 HxWx3 RGB (the colours); uncertainty: float HxW, needed
    with `max_uncertainty` (pixels above it are dropped); limits: see `DepthRange` (its depth
    limit applies to metric points only).
    """
    height, width = disparity.shape
    if left.shape[:2] != (height, width):
        raise ValueError(f"left image {left.shape[:2]} and disparity {disparity.shape} differ in size")
    depth = None if focal_baseline is None else metric_depth(disparity, focal_baseline, limits)
    keep = np.isfinite(disparity) & (disparity > limits.min_disparity) if depth is None else np.isfinite(depth)
    if max_uncertainty is not None:
        if uncertainty is None:
            raise ValueError("max_uncertainty needs the uncertainty map")
        keep &= uncertainty <= max_uncertainty
    v, u = np.nonzero(keep)
    if focal_baseline is None or depth is None:
        points = np.stack([u, v, disparity[keep].astype(np.float64)], axis=1)
    else:
        cx = (width - 1) / 2 if focal_baseline.cx is None else focal_baseline.cx
        cy = (height - 1) / 2 if focal_baseline.cy is None else focal_baseline.cy
        z = depth[keep].astype(np.float64)
        focal = focal_baseline.focal_px
        points = np.stack([(u - cx) * z / focal, (v - cy) * z / focal, z], axis=1)
    return points.astype(np.float32), np.ascontiguousarray(left[keep][:, :3]).astype(np.uint8)


METRIC_FRAME = "units metres; frame: left camera, x right, y down, z forward"
IMAGE_FRAME = "units pixels; x = column, y = row, z = disparity (left image)"


_VERTEX = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
"""One vertex of the PLY files written here."""
_END_HEADER = b"end_header\n"


def encode_ply(points: np.ndarray, colors: np.ndarray, frame: str, comments: Sequence[str] = ()) -> bytes:
    """Binary little-endian PLY of float32 x, y, z and uint8 red, green, blue per vertex; `frame`
    (METRIC_FRAME or IMAGE_FRAME) is written as a header comment, then each of `comments` (one
    line of ASCII each)."""
    if points.ndim != 2 or points.shape[1] != 3 or colors.shape != points.shape:
        raise ValueError(f"expected Nx3 points and Nx3 colours, got {points.shape} and {colors.shape}")
    if any(not comment.isascii() or "\n" in comment or "\r" in comment for comment in comments):
        raise ValueError("a PLY header comment is one line of ASCII")
    vertex = np.empty(len(points), dtype=_VERTEX)
    vertex["x"], vertex["y"], vertex["z"] = points[:, 0], points[:, 1], points[:, 2]
    vertex["red"], vertex["green"], vertex["blue"] = colors[:, 0], colors[:, 1], colors[:, 2]
    header = (
        f"ply\nformat binary_little_endian 1.0\ncomment crestereo-pp point cloud\ncomment {frame}\n"
        + "".join(f"comment {comment}\n" for comment in comments)
        + f"element vertex {len(points)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
    )
    return header.encode("ascii") + _END_HEADER + vertex.tobytes()


class DecodedPly(NamedTuple):
    """A PLY file `encode_ply` wrote: points float32 Nx3, colours uint8 Nx3 RGB, its frame
    (METRIC_FRAME or IMAGE_FRAME) and its other header comments, in order."""

    points: np.ndarray
    colors: np.ndarray
    frame: str
    comments: list[str]


def decode_ply(data: bytes) -> DecodedPly:
    """The points, colours, frame and comments of a PLY file `encode_ply` wrote. ValueError for any
    other file."""
    end = data.find(_END_HEADER)
    lines = data[: max(end, 0)].decode("ascii", errors="replace").splitlines()
    frames = [frame for frame in (METRIC_FRAME, IMAGE_FRAME) if f"comment {frame}" in lines]
    counts = [line.removeprefix("element vertex ") for line in lines if line.startswith("element vertex ")]
    if end < 0 or len(frames) != 1 or len(counts) != 1 or not counts[0].isdigit():
        raise ValueError("not a point cloud of this project's binary PLY")
    body = data[end + len(_END_HEADER) :]
    count = int(counts[0])
    if len(body) != count * _VERTEX.itemsize:
        raise ValueError(f"the PLY file says {count} points but holds {len(body)} bytes of them")
    vertex = np.frombuffer(body, dtype=_VERTEX)
    points = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1)
    colors = np.stack([vertex["red"], vertex["green"], vertex["blue"]], axis=1)
    own = {"comment crestereo-pp point cloud", f"comment {frames[0]}"}
    comments = [line.removeprefix("comment ") for line in lines if line.startswith("comment ") and line not in own]
    return DecodedPly(points, colors, frames[0], comments)
