"""What the procedural scenes draw for the cases stereo networks get wrong on cluttered real scenes
(Middlebury-2014-like rooms) and on driving scenes: thin structures in front of far backgrounds,
large weakly textured planes with slow shading, repetitive patterns, wide disparity ranges and
surfaces that reflect a farther scene (see `SceneConfig`).

Each option is off by default, and an option that is off draws nothing from the scene's random
generator: a seed then gives the same batch, bit for bit, as before these options existed.
The scenes' sampling and textures (`sampling`, `textures`) apply what is drawn here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .config import SceneConfig
from .draw import Draw

THIN_WIDTH = (1.0, 6.0)
"""Full width of thin structures, output px (not magnified by the scene's scale), log-uniform; at
least a pixel, so that the pixel centres never break one into dashes."""
FLAT_RADIUS = (0.25, 0.5)
"""Radius of flat foreground surfaces as a share of the frame width before the scene's scale, uniform."""
FLAT_CONTRAST = (1.0, 4.0)
"""Grey-level std of a flat surface's texture, log-uniform (other surfaces: `SceneConfig.contrast`)."""
FLAT_SHADING = (1 / 3, 1.0)
"""Brightness ramp across a flat surface as a share of `SceneConfig.shading`, uniform."""
REPETITIVE_PERIOD = (4.0, 40.0)
"""Period of repetitive patterns along the rows, output px (not magnified), log-uniform."""
REPETITIVE_TILT = math.radians(10.0)
"""Repetitive patterns are turned by at most this (radians) from repeating along the rows, the
epipolar lines, where their ambiguity bites."""
REPETITIVE_TEXTURES = 2
"""Repetitive patterns in each scene's texture bank, after the `SceneConfig.texture_count` others."""
REFLECTION_CONTRAST = (4.0, 40.0)
"""Grey-level std of a reflective surface's reflection, log-uniform: from a faint sheen to a car's
window (a surface's own texture: `SceneConfig.contrast`)."""
REFLECTION_DEPTH = (0.0, 0.8)
"""The reflected scene's disparity as a share of the reflecting surface's, uniform: 0 is the sky at
infinity; what a mirror, or a car's convex body, shows lies behind it, so the share stays below 1."""
_REPETITIVE_CYCLE = 16
"""Texels per period of the repetitive patterns, nominal (see `repetitive_period_texels`)."""


def repetitive_period_texels(texture_size: int) -> float:
    """Texels per period of the repetitive patterns: a whole number of periods fits the (wrapping)
    texture of ``texture_size`` texels, the nearest to `_REPETITIVE_CYCLE` texels each."""
    return texture_size / max(1, round(texture_size / _REPETITIVE_CYCLE))


@dataclass
class SurfaceKinds:
    """Which surfaces of B scenes of S slots (slot 0 the background) are of a special kind, and what
    was drawn for them; every field (B, S), meaningful only where its kind is true.

    thin: foreground surfaces that are thin bars `thin_width` px wide (wires, stems, pipes, chair
        legs), lying in the nearer half of the scene's disparity range.
    flat: large, weakly textured planes (walls, tables, floors; the background may be one):
        foreground ones of radius `flat_radius` (share of the frame width, before the scene's
        scale); texture std `flat_contrast` grey levels; a brightness ramp of `flat_shading` grey
        levels across the surface. Never thin.
    repetitive: surfaces showing repetitive pattern `repetitive_texture` in [0, REPETITIVE_TEXTURES)
        with a period of `repetitive_period` px, turned by `repetitive_tilt` radians from repeating
        along the rows. Never flat, never the background.
    reflective: foreground surfaces that reflect a farther scene: a texture of std
        `reflection_contrast` grey levels over their own, at `reflection_depth` times their
        disparity (`REFLECTION_DEPTH`). Never thin, never the background.
    """

    thin: torch.Tensor
    thin_width: torch.Tensor
    flat: torch.Tensor
    flat_radius: torch.Tensor
    flat_contrast: torch.Tensor
    flat_shading: torch.Tensor
    repetitive: torch.Tensor
    repetitive_texture: torch.Tensor
    repetitive_period: torch.Tensor
    repetitive_tilt: torch.Tensor
    reflective: torch.Tensor
    reflection_contrast: torch.Tensor
    reflection_depth: torch.Tensor

    @staticmethod
    def draw(shape: tuple[int, int], cfg: SceneConfig, draw: Draw) -> SurfaceKinds:
        """The kinds of (B, S) surfaces; a kind whose probability is 0 is nowhere, and draws nothing."""
        none = torch.zeros(shape, dtype=torch.bool, device=draw.device)
        zero = torch.zeros(shape, device=draw.device)
        thin, thin_width = none, zero
        if cfg.thin_probability > 0:
            thin = draw.chance(shape, cfg.thin_probability)
            thin[:, 0] = False  # the background covers the frame
            thin_width = draw.log_uniform(shape, *THIN_WIDTH)
        flat, flat_radius, flat_contrast, flat_shading = none, zero, zero, zero
        if cfg.flat_probability > 0:
            flat = draw.chance(shape, cfg.flat_probability) & ~thin
            flat_radius = draw.uniform(shape, *FLAT_RADIUS)
            flat_contrast = draw.log_uniform(shape, *FLAT_CONTRAST)
            flat_shading = cfg.shading * draw.uniform(shape, *FLAT_SHADING)
        repetitive, repetitive_texture, repetitive_period, repetitive_tilt = none, none.long(), zero, zero
        if cfg.repetitive_probability > 0:
            repetitive = draw.chance(shape, cfg.repetitive_probability) & ~flat
            repetitive[:, 0] = False  # covering the frame, it would be ambiguous by whole periods everywhere
            repetitive_texture = draw.integers(shape, 0, REPETITIVE_TEXTURES - 1)
            repetitive_period = draw.log_uniform(shape, *REPETITIVE_PERIOD)
            repetitive_tilt = draw.uniform(shape, -REPETITIVE_TILT, REPETITIVE_TILT)
        reflective, reflection_contrast, reflection_depth = none, zero, zero
        if cfg.reflective_probability > 0:
            reflective = draw.chance(shape, cfg.reflective_probability) & ~thin
            reflective[:, 0] = False  # covering the frame, no outline would tell it from its reflection
            reflection_contrast = draw.log_uniform(shape, *REFLECTION_CONTRAST)
            reflection_depth = draw.uniform(shape, *REFLECTION_DEPTH)
        return SurfaceKinds(
            thin,
            thin_width,
            flat,
            flat_radius,
            flat_contrast,
            flat_shading,
            repetitive,
            repetitive_texture,
            repetitive_period,
            repetitive_tilt,
            reflective,
            reflection_contrast,
            reflection_depth,
        )


def scene_max_disparity(batch_size: int, cfg: SceneConfig, draw: Draw) -> float | torch.Tensor:
    """Each scene's largest disparity, px: ``cfg.max_disparity``, or for a wide-range scene (drawn
    with ``cfg.wide_range_probability``) uniform in [max_disparity, wide_max_disparity]. A (B,)
    tensor where the option is on; else the number itself, so that scenes are computed as before."""
    assert cfg.max_disparity is not None and cfg.wide_max_disparity is not None  # resolved by SceneConfig
    if cfg.wide_range_probability == 0:
        return float(cfg.max_disparity)
    wide = draw.chance((batch_size,), cfg.wide_range_probability)
    return torch.where(wide, draw.uniform((batch_size,), cfg.max_disparity, cfg.wide_max_disparity), cfg.max_disparity)
