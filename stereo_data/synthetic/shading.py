"""The colour a view sees of a surface point: its texture, shading ramp, light, highlight and
the farther scene it reflects."""

from __future__ import annotations

from collections.abc import Callable

import torch

from .geometry import surface_disparity, surface_gradient
from .scene import Scene


def shade(scene: Scene, surface: torch.Tensor, x_left: torch.Tensor, y: torch.Tensor, view: str) -> torch.Tensor:
    """Colour of the given surfaces at left-view points, as the ``view`` camera ("left" or
    "right") sees them (they differ only in highlights and reflections).

    surface: (B, 1, H, W) int64 surface index; x_left: (B, 1, H, W) px; y: (1, 1, H, 1) px.
    Returns (B, 3, H, W) float32 RGB in [0, 255].
    """
    batch, surfaces = scene.sides.shape
    batch_index = torch.arange(batch, device=surface.device).view(batch, 1, 1, 1).expand_as(surface)
    flat_surface = (batch_index * surfaces + surface).flatten()

    def at_pixels(values: torch.Tensor) -> torch.Tensor:
        """(B, S, ...) per-surface values -> (N, ...) values of each pixel's surface, N = B*H*W."""
        return values.flatten(0, 1).index_select(0, flat_surface)

    x, y = x_left.flatten(), y.expand_as(x_left).flatten()
    point = torch.stack([x, y, torch.ones_like(x)], dim=-1)  # (N, 3)
    texel_u, texel_v = (at_pixels(scene.to_texture) * point[:, None, :]).sum(-1).unbind(-1)
    contrast = at_pixels(scene.contrast)
    if scene.projective.any():
        projective = at_pixels(scene.projective)
        plane, curvature, apex = (at_pixels(value) for value in (scene.plane, scene.curvature, scene.apex))
        disparity = surface_disparity(plane, curvature, apex, x, y)
        fade = at_pixels(scene.fade_disparity).clamp_min(1e-6)
        depth = torch.where(projective, 1 / torch.maximum(disparity, fade), 1.0)
        texel_u, texel_v = texel_u * depth, texel_v * depth
        contrast = torch.where(projective, contrast * (disparity / fade - 1).clamp(0, 1), contrast)
    slot = batch_index.flatten() * scene.textures.shape[1] + at_pixels(scene.texture)
    texture = _sample_wrapped(scene.textures.flatten(0, 1), slot, texel_u, texel_v)  # (N, 3)
    shading = (at_pixels(scene.ramp) * point).sum(-1, keepdim=True)
    color = at_pixels(scene.base) + contrast[:, None] * texture
    if (scene.ambient < 1).any() or scene.specular.any():
        color = _lit(scene, at_pixels, batch_index.flatten(), x, y, color, view)
    color = color + shading
    if scene.reflection.any():  # computed on the points of reflective surfaces only
        reflecting = torch.nonzero(at_pixels(scene.reflection)).squeeze(1)

        def at_reflecting(values: torch.Tensor) -> torch.Tensor:
            """(B, S, ...) per-surface values -> (n, ...) values of each reflecting point's surface."""
            return values.flatten(0, 1).index_select(0, flat_surface[reflecting])

        seen = (batch_index.flatten()[reflecting], x[reflecting], y[reflecting])
        color = color.index_add(0, reflecting, _reflected(scene, at_reflecting, *seen, view))
    return color.clamp(0, 255).view(batch, *surface.shape[2:], 3).permute(0, 3, 1, 2).contiguous()


def _lit(
    scene: Scene,
    at_pixels: Callable[[torch.Tensor], torch.Tensor],
    scene_index: torch.Tensor,
    x: torch.Tensor,
    y: torch.Tensor,
    color: torch.Tensor,
    view: str,
) -> torch.Tensor:
    """`color` (N, 3) of surface points at left-view (x, y) (N,) px under the scene's light, seen
    from the ``view`` camera: Lambertian shading by the point's normal plus its highlight."""
    plane, curvature, apex = (at_pixels(value) for value in (scene.plane, scene.curvature, scene.apex))
    gradient_x, gradient_y = surface_gradient(plane, curvature, apex, x, y)
    relief = scene.relief[scene_index]
    normal = torch.stack([-relief * gradient_x, -relief * gradient_y, -torch.ones_like(x)], dim=-1)
    normal = normal / normal.norm(dim=-1, keepdim=True)
    light = scene.light[scene_index]
    ambient = scene.ambient[scene_index, None]
    diffuse = (normal * light).sum(-1, keepdim=True).clamp_min(0)
    focal, centre_x, centre_y = scene.camera[scene_index].unbind(-1)
    x_view = x - surface_disparity(plane, curvature, apex, x, y) if view == "right" else x
    to_camera = torch.stack([(centre_x - x_view) / focal, (centre_y - y) / focal, -torch.ones_like(x)], dim=-1)
    half = light + to_camera / to_camera.norm(dim=-1, keepdim=True)
    half = half / half.norm(dim=-1, keepdim=True)
    gloss: torch.Tensor = (normal * half).sum(-1).clamp_min(0) ** at_pixels(scene.shininess)
    highlight = (at_pixels(scene.specular) * gloss)[:, None]
    lit: torch.Tensor = color * (ambient + (1 - ambient) * diffuse) + highlight
    return lit


def _reflected(
    scene: Scene,
    at_pixels: Callable[[torch.Tensor], torch.Tensor],
    scene_index: torch.Tensor,
    x: torch.Tensor,
    y: torch.Tensor,
    view: str,
) -> torch.Tensor:
    """(N, 3) grey levels that the surface points at left-view (x, y) (N,) px add from the farther
    scene they reflect, as the ``view`` camera sees it: the right camera sees at the point's
    x - d the reflection's texel that the left sees at x - d + reflection_depth * d."""
    if view == "right":
        plane, curvature, apex = (at_pixels(value) for value in (scene.plane, scene.curvature, scene.apex))
        x = x - (1 - at_pixels(scene.reflection_depth)) * surface_disparity(plane, curvature, apex, x, y)
    point = torch.stack([x, y, torch.ones_like(x)], dim=-1)
    texel_u, texel_v = (at_pixels(scene.to_reflection) * point[:, None, :]).sum(-1).unbind(-1)
    slot = scene_index * scene.textures.shape[1] + at_pixels(scene.reflection_texture)
    return at_pixels(scene.reflection)[:, None] * _sample_wrapped(scene.textures.flatten(0, 1), slot, texel_u, texel_v)


def _sample_wrapped(textures: torch.Tensor, slot: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of periodic textures: textures (N_t, T, T, 3); slot, u, v (N,) with u the
    column and v the row in texels (any real value: the textures wrap). Returns (N, 3)."""
    size = textures.shape[1]
    texels = textures.reshape(-1, 3)
    u_floor, v_floor = torch.floor(u), torch.floor(v)
    u_weight, v_weight = (u - u_floor)[:, None], (v - v_floor)[:, None]
    u0, v0 = torch.remainder(u_floor.long(), size), torch.remainder(v_floor.long(), size)
    u1, v1 = torch.remainder(u0 + 1, size), torch.remainder(v0 + 1, size)
    first = slot * size * size

    def texel(row: torch.Tensor, column: torch.Tensor) -> torch.Tensor:
        return texels.index_select(0, first + row * size + column)

    top = (1 - u_weight) * texel(v0, u0) + u_weight * texel(v0, u1)
    bottom = (1 - u_weight) * texel(v1, u0) + u_weight * texel(v1, u1)
    return (1 - v_weight) * top + v_weight * bottom
