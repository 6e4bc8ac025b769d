"""The z-buffer: which surface each sample of a view sees (the largest disparity wins)."""

from __future__ import annotations

import math

import torch

from .geometry import covers, seen_from_right, surface_disparity
from .scene import Scene


def nearest_surface(
    scene: Scene, x: torch.Tensor, y: torch.Tensor, view: str
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The nearest surface at each query point of one view (z-buffer: the largest disparity wins).

    x: query x in the ``view`` ("left" or "right") image, px: (1, 1, 1, W) columns shared by
        every row (a view's sample grid, ascending), or (B, 1, H, W) one per point.
    y: (1, 1, H, 1) rows, px, ascending.
    Returns the winner's disparity (B, 1, H, W) px, its index (B, 1, H, W) int64, and the left-view
    x of the winner's point (B, 1, H, W) px. Each surface is evaluated only on the rows (and, for
    shared columns, the columns) its bounding box in the view can reach (`view_bounds`); ties go
    to the lowest index.
    """
    batch, surfaces = scene.sides.shape
    shape = (batch, 1, y.shape[-2], x.shape[-1])
    nearest = torch.full(shape, -math.inf, dtype=x.dtype, device=x.device)
    index = torch.zeros(shape, dtype=torch.int64, device=x.device)
    x_nearest = x.expand(shape).clone()
    low_x, high_x, low_y, high_y = view_bounds(scene, view).unbind(-1)  # (B, S) each
    rows = _spans(y.flatten(), low_y.amin(0), high_y.amax(0))
    shared_columns = x.shape[-2] == 1
    columns = _spans(x.flatten(), low_x.amin(0), high_x.amax(0)) if shared_columns else [slice(0, shape[-1])] * surfaces
    present = scene.present.any(0).tolist()
    for surface in range(surfaces):
        row, column = rows[surface], columns[surface]
        if not present[surface] or row.start >= row.stop or column.start >= column.stop:
            continue
        part = scene.surfaces(slice(surface, surface + 1))
        y_part = y[:, :, row]
        x_part = x[..., column] if shared_columns else x[:, :, row]
        x_left = x_part if view == "left" else seen_from_right(part, x_part, y_part)
        plane, curvature, apex = (value[:, :, None, None] for value in (part.plane, part.curvature, part.apex))
        disparity = surface_disparity(plane, curvature, apex, x_left, y_part)
        disparity = torch.where(covers(part, x_left, y_part), disparity, -math.inf)
        region = (slice(None), slice(None), row, column)
        nearer = disparity > nearest[region]
        nearest[region] = torch.where(nearer, disparity, nearest[region])
        index[region] = index[region].masked_fill(nearer, surface)
        x_nearest[region] = torch.where(nearer, x_left.expand_as(disparity), x_nearest[region])
    return nearest, index, x_nearest


_BOUNDS_MARGIN_PX = 2.0
"""`view_bounds` widens every box by this much: the root of `seen_from_right` and the
shape test are float computations, so a point at a box's edge must not be culled by rounding."""


def view_bounds(scene: Scene, view: str) -> torch.Tensor:
    """(B, S, 4): (low x, high x, low y, high y) px, a box in the ``view`` image that holds every
    point of each surface (infinite where the shape is unbounded, as the background's is).

    The shape lies within the disk of its largest vertex radius in the shape frame; to_shape's
    inverse maps that disk to an ellipse in the left view. A right-view point is at
    x - d(x, y) for the left-view point (x, y): the box moves left by the surface's disparity,
    bounded over the left box (the plane's at the corners, the quadratic term by its largest
    magnitude)."""
    linear, offset = scene.to_shape[..., :2], scene.to_shape[..., 2]
    m00, m01, m10, m11 = linear.flatten(-2).unbind(-1)
    det = m00 * m11 - m01 * m10
    bounded = det.abs() > 1e-12
    inverse_det = torch.where(bounded, 1 / torch.where(bounded, det, 1.0), math.inf)
    radius = scene.radii.amax(-1)
    centre_x = -(m11 * offset[..., 0] - m01 * offset[..., 1]) * inverse_det
    centre_y = -(-m10 * offset[..., 0] + m00 * offset[..., 1]) * inverse_det
    reach_x = radius * torch.hypot(m11, m01) * inverse_det.abs() + _BOUNDS_MARGIN_PX
    reach_y = radius * torch.hypot(m10, m00) * inverse_det.abs() + _BOUNDS_MARGIN_PX
    low_x, high_x = centre_x - reach_x, centre_x + reach_x
    low_y, high_y = centre_y - reach_y, centre_y + reach_y
    low_x, high_x, low_y, high_y = (
        torch.where(bounded, value, fill)
        for value, fill in ((low_x, -math.inf), (high_x, math.inf), (low_y, -math.inf), (high_y, math.inf))
    )
    if view == "left":
        return torch.stack([low_x, high_x, low_y, high_y], dim=-1)
    a, b, c = scene.plane.unbind(-1)
    plane_low = c + torch.minimum(a * low_x, a * high_x) + torch.minimum(b * low_y, b * high_y)
    plane_high = c + torch.maximum(a * low_x, a * high_x) + torch.maximum(b * low_y, b * high_y)
    kxx, kxy, kyy = scene.curvature.abs().unbind(-1)
    u = torch.maximum((low_x - scene.apex[..., 0]).abs(), (high_x - scene.apex[..., 0]).abs())
    v = torch.maximum((low_y - scene.apex[..., 1]).abs(), (high_y - scene.apex[..., 1]).abs())
    quadratic = torch.where(scene.curvature.any(-1), kxx * u * u + kxy * u * v + kyy * v * v, 0.0)
    # unbounded shapes keep infinite boxes (their plane terms would be 0 * inf = nan)
    high_right = torch.where(bounded, high_x - (plane_low - quadratic), math.inf)
    low_right = torch.where(bounded, low_x - (plane_high + quadratic), -math.inf)
    return torch.stack([low_right, high_right, low_y, high_y], dim=-1)


def _spans(positions: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> list[slice]:
    """For ascending ``positions`` (N,) px and per-surface bounds (S,) px: the slice of positions
    within [low, high] of each surface."""
    starts = torch.searchsorted(positions, low.contiguous(), side="left").tolist()
    stops = torch.searchsorted(positions, high.contiguous(), side="right").tolist()
    return [slice(start, stop) for start, stop in zip(starts, stops, strict=True)]
