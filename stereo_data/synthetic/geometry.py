"""A surface's geometry: its disparity and gradient at a point, where a right-view pixel meets it,
and whether its shape covers a point."""

from __future__ import annotations

import math

import torch

from .scene import MAX_SIDES, Scene


def _apply(affine: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Apply (B, S, 2, 3) affine maps to points: x broadcastable to (B, S, H, W), y (1, 1, H, 1)."""
    m = affine[..., None, None]  # (B, S, 2, 3, 1, 1)
    u, v = (m[:, :, row, 0] * x + (m[:, :, row, 1] * y + m[:, :, row, 2]) for row in (0, 1))
    return u, v


def surface_disparity(
    plane: torch.Tensor, curvature: torch.Tensor, apex: torch.Tensor, x: torch.Tensor, y: torch.Tensor
) -> torch.Tensor:
    """Disparity (px) of surfaces at left-view points (x, y) px: a*x + b*y + c plus the quadratic
    term kxx*u^2 + kxy*u*v + kyy*v^2, (u, v) = (x, y) - apex. plane and curvature (..., 3), apex
    (..., 2): per-surface parameters (see `Scene`) whose leading dimensions broadcast with x and y."""
    a, b, c = plane.unbind(-1)
    disparity = a * x + (b * y + c)
    if not curvature.any():
        return disparity
    kxx, kxy, kyy = curvature.unbind(-1)
    u, v = x - apex[..., 0], y - apex[..., 1]
    return disparity + (kxx * u + kxy * v) * u + kyy * v * v


def surface_gradient(
    plane: torch.Tensor, curvature: torch.Tensor, apex: torch.Tensor, x: torch.Tensor, y: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """(d_x, d_y): the gradient of `surface_disparity` (px per px) at the same points."""
    kxx, kxy, kyy = curvature.unbind(-1)
    u, v = x - apex[..., 0], y - apex[..., 1]
    return plane[..., 0] + 2 * kxx * u + kxy * v, plane[..., 1] + kxy * u + 2 * kyy * v


def seen_from_right(scene: Scene, x_right: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """(B, S, H, W): for each surface, the left-view x of its point seen at right-view x_right,
    i.e. x_l solving x_l - d(x_l, y) = x_right. x_right broadcastable to (B, 1, H, W) px.

    For a curved surface, with x_l = x0 + u, that is the quadratic A*u^2 + B*u + C = 0 where
    A = kxx, B = a + kxy*v - 1 and C = a*x0 + b*y + c + kyy*v^2 - x0 + x_right: its root on the branch
    where d grows slower than x (d_x < 1, which holds within every shape) is
    u = -2C / (B - sqrt(B^2 - 4AC)), the plane's root when A = 0. Points with no root on that branch
    get a point outside the shape (where the quadratic folds back)."""
    a, b, c = (part[..., None, None] for part in scene.plane.unbind(-1))
    if not scene.curvature.any():
        return (x_right + (b * y + c)) / (1 - a)
    kxx, kxy, kyy = (part[..., None, None] for part in scene.curvature.unbind(-1))
    x0, y0 = (part[..., None, None] for part in scene.apex.unbind(-1))
    v = y - y0
    linear = a + kxy * v - 1
    constant = a * x0 + (b * y + c) + kyy * v * v - x0 + x_right
    root = torch.sqrt((linear * linear - 4 * kxx * constant).clamp_min(0))
    return x0 - 2 * constant / (linear - root).clamp_max(-1e-6)


def covers(scene: Scene, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """(B, S, H, W) bool: whether each surface's shape contains its point (x, y)."""
    u, v = _apply(scene.to_shape, x, y)
    batch, surfaces = scene.sides.shape
    # The polygon's sector holding each point, then the side of that sector's edge line it is on.
    sides = scene.sides[..., None, None].to(u.dtype)
    sector_angle = torch.remainder(torch.atan2(v, u) - scene.phase[..., None, None], 2 * math.pi)
    sector = (sector_angle * (sides / (2 * math.pi))).long()  # in [0, sides]: sides is edge 0 again
    edges = _polygon_edges(scene)
    flat_sector = sector.view(batch, surfaces, -1)
    normal_u, normal_v, offset = (torch.gather(edges[..., k], 2, flat_sector).view_as(u) for k in range(3))
    inside = normal_u * u + normal_v * v <= offset
    u0, v0, ru, rv = (part[..., None, None] for part in scene.hole.unbind(-1))
    in_hole = ((u - u0) * (1 / ru)).square() + ((v - v0) * (1 / rv)).square() < 1
    return inside & ~(in_hole & scene.has_hole[..., None, None]) & scene.present[..., None, None]


def _polygon_edges(scene: Scene) -> torch.Tensor:
    """(B, S, MAX_SIDES + 1, 3): edge j, from vertex j to vertex j+1 (indices modulo sides), as its
    outward normal (nu, nv) and offset h; a point of sector j is inside when nu*u + nv*v <= h."""
    index = torch.arange(MAX_SIDES + 2, device=scene.sides.device)
    sides = scene.sides[..., None]
    angle = scene.phase[..., None] + 2 * math.pi * index / sides  # (B, S, MAX_SIDES + 2)
    radius = torch.gather(scene.radii, 2, torch.remainder(index, sides))
    vertex = radius[..., None] * torch.stack([torch.cos(angle), torch.sin(angle)], dim=-1)
    vertex, next_vertex = vertex[:, :, :-1], vertex[:, :, 1:]
    step = next_vertex - vertex
    normal = torch.stack([step[..., 1], -step[..., 0]], dim=-1)
    offset = (normal * vertex).sum(-1, keepdim=True)
    return torch.cat([normal, offset], dim=-1)
