"""Road and room layouts: a ground plane (or floor) seen in perspective under a sky (or before a
back wall)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .config import SceneConfig
from .draw import Draw


@dataclass
class Road:
    """The layout of road and room scenes: surface 0 becomes a far sky (roads) or a back wall
    (rooms), surface 1 the ground (a floor, in rooms).

    The ground is the plane d = a*(x - cx) + b*(y - horizon) px (cx the frame's centre column): zero
    at the horizon, growing downwards by b px per row (b = baseline / camera height), tilted by a
    small camera roll (a). Above the horizon it is behind the sky, so the z-buffer cuts it there. In
    a room the horizon lies above the row where the floor meets the back wall (the floor's
    disparity there is the wall's), and the wall cuts the floor above that row.
    Its texture is fixed to the ground and seen through a pinhole of focal length f px: texel
    coordinates (u, v) = (q * (x - cx) / d, f * q / d) plus offsets, square on the ground, q chosen
    so that texels are ``ground_texel`` px wide at the bottom row; so rows nearer the horizon show
    the texture smaller and squashed, and it fades out where its texels get finer than the
    sample.

    present: (B,) bool, which scenes are road or room scenes; sky: (B,) bool, the road scenes.
    planes: (B, 2, 3) the (a, b, c) planes of surfaces 0 (the sky or wall, fronto-parallel) and 1 (the ground).
    to_texture: (B, 2, 3) the ground's texture map, to be divided by its disparity (projective).
    fade_disparity: (B,) px, see `Scene.fade_disparity`.
    sky_contrast: (B,) grey levels: the sky is weakly textured.
    """

    present: torch.Tensor
    sky: torch.Tensor
    planes: torch.Tensor
    to_texture: torch.Tensor
    fade_disparity: torch.Tensor
    sky_contrast: torch.Tensor

    @staticmethod
    def draw(batch_size: int, max_disparity: float | torch.Tensor, cfg: SceneConfig, draw: Draw) -> Road:
        """The layouts of B scenes under each one's largest disparity, `max_disparity` px (one number, or (B,))."""
        height, width = cfg.height, cfg.width
        shape = (batch_size,)
        sky = draw.chance(shape, cfg.road_probability)
        horizon = height * draw.uniform(shape, -0.5, 0.6)  # may lie above the frame
        roll = draw.uniform(shape, -0.08, 0.08)  # a / b, about +-4.5 degrees
        # The ground's nearest point in the frame (a bottom corner) stays within 0.95 * max.
        reach = height - 1 - horizon + roll.abs() * (width - 1) / 2
        slope = torch.minimum(draw.log_uniform(shape, 0.15, 0.8), 0.95 * max_disparity / reach)
        focal = height * draw.log_uniform(shape, 2.0, 8.0)
        ground_texel = draw.log_uniform(shape, 3.0, 32.0)  # px, at the bottom row
        offset_u, offset_v = draw.uniform((2, batch_size), 0, cfg.texture_size)
        sky_disparity = draw.uniform(shape, 0, 0.02 * max_disparity)
        sky_contrast = draw.log_uniform(shape, 1.0, 6.0)
        present, far_disparity = sky, sky_disparity  # far: the sky's disparity, or the wall's in rooms
        if cfg.room_probability > 0:  # drawn only then: road scenes stay as they were without rooms
            room = draw.chance(shape, cfg.room_probability) & ~sky
            present = sky | room
            junction = height * draw.uniform(shape, 0.25, 0.9)  # the row where the floor meets the wall
            wall = max_disparity * draw.uniform(shape, 0.1, 0.45)
            reach_below = height - 1 - junction + roll.abs() * (width - 1) / 2
            room_slope = torch.minimum(draw.log_uniform(shape, 0.15, 0.8), (0.95 * max_disparity - wall) / reach_below)
            horizon = torch.where(room, junction - wall / room_slope, horizon)
            slope = torch.where(room, room_slope, slope)
            far_disparity = torch.where(room, wall, sky_disparity)

        centre = (width - 1) / 2
        a, b = roll * slope, slope
        c = -a * centre - b * horizon
        zero = torch.zeros_like(a)
        background = torch.stack([zero, zero, far_disparity], dim=-1)
        ground = torch.stack([a, b, c], dim=-1)
        q = b * (height - 1 - horizon) / ground_texel  # texel width d / q px at disparity d
        # Numerators of u and v, each an affine function of (x, y); the offsets ride on d itself.
        to_texture = torch.stack(
            [
                torch.stack([q + offset_u * a, offset_u * b, -q * centre + offset_u * c], dim=-1),
                torch.stack([offset_v * a, offset_v * b, focal * q + offset_v * c], dim=-1),
            ],
            dim=-2,
        )
        # Texels are d / q px wide and d^2 / (f q b) px tall: both at least a sample (1 / supersample px).
        smallest = 1 / cfg.supersample
        fade = torch.maximum(q * smallest, torch.sqrt(focal * q * b * smallest))
        return Road(present, sky, torch.stack([background, ground], dim=1), to_texture, fade, sky_contrast)

    def disparity(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """The ground's disparity (px) at points x, y (B, n) px; negative above the horizon."""
        a, b, c = self.planes[:, 1, :, None].unbind(1)
        return a * x + b * y + c
