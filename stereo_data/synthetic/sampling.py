"""Drawing scenes: every surface's shape, disparity, look and lighting (`draw_scenes`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .config import SceneConfig
from .draw import Draw
from .hard_cases import SurfaceKinds, repetitive_period_texels, scene_max_disparity
from .layouts import Road
from .scene import MAX_SIDES, Scene
from .textures import texture_bank


def draw_scenes(batch_size: int, cfg: SceneConfig, draw: Draw, photos: list[torch.Tensor]) -> Scene:
    """`batch_size` scenes drawn from `cfg`, each with its surfaces (slot 0 the background, then
    `cfg.surfaces` foreground slots) and its texture bank; `photos` are the photo textures' sources
    (`stereo_data.photos.load_photos`, empty without photo textures)."""
    shape = (batch_size, cfg.surfaces + 1)  # surface 0 is the background
    scale = 2 ** draw.uniform((batch_size, 1), *cfg.log2_scale)  # magnification s
    kinds = SurfaceKinds.draw(shape, cfg, draw)
    max_disparity = scene_max_disparity(batch_size, cfg, draw)
    shapes, road = _Shapes.draw(shape, scale, kinds, max_disparity, cfg, draw)
    plane, curvature = _disparity_planes(shapes, road, kinds, max_disparity, cfg, draw)
    look = _Appearance.draw(shapes, road, scale, kinds, cfg, draw)
    lighting = _Lighting.draw(shape, cfg, draw) if cfg.lighting_probability > 0 else _Lighting.none(shape, cfg, draw)
    return Scene(
        plane=plane,
        curvature=curvature,
        apex=torch.stack([shapes.centre_x, shapes.centre_y], dim=-1),
        to_shape=shapes.to_shape,
        sides=shapes.sides,
        phase=shapes.phase,
        radii=shapes.radii,
        hole=shapes.hole,
        has_hole=shapes.has_hole,
        present=shapes.present,
        texture=look.texture,
        to_texture=look.to_texture,
        projective=look.projective,
        fade_disparity=look.fade_disparity,
        base=look.base,
        contrast=look.contrast,
        ramp=look.ramp,
        reflection=look.reflection,
        reflection_depth=look.reflection_depth,
        reflection_texture=look.reflection_texture,
        to_reflection=look.to_reflection,
        specular=lighting.specular,
        shininess=lighting.shininess,
        light=lighting.light,
        ambient=lighting.ambient,
        relief=lighting.relief,
        camera=lighting.camera,
        textures=texture_bank(batch_size, cfg, draw, photos),
    )


@dataclass
class _Shapes:
    """Where each surface is and what outline it has (see `Scene`), in output px; `extent`
    (B, S): the shape lies within this distance of its centre (centre_x, centre_y) (B, S)."""

    centre_x: torch.Tensor
    centre_y: torch.Tensor
    extent: torch.Tensor
    to_shape: torch.Tensor
    sides: torch.Tensor
    phase: torch.Tensor
    radii: torch.Tensor
    hole: torch.Tensor
    has_hole: torch.Tensor
    present: torch.Tensor

    @staticmethod
    def draw(
        shape: tuple[int, int],
        scale: torch.Tensor,
        kinds: SurfaceKinds,
        max_disparity: float | torch.Tensor,
        cfg: SceneConfig,
        draw: Draw,
    ) -> tuple[_Shapes, Road | None]:
        """The shapes of B scenes of S surfaces magnified by `scale` (B, 1), thin ones bars and flat
        ones large (`kinds`), and the road layout where the config has roads (it reshapes surfaces 0
        and 1) under each scene's `max_disparity` px (see `scene_max_disparity`)."""
        height, width = cfg.height, cfg.width
        batch_size = shape[0]
        centre_x = draw.uniform(shape, -0.1 * width, 1.1 * width)
        centre_y = draw.uniform(shape, -0.1 * height, 1.1 * height)
        radius = scale * width * draw.log_uniform(shape, *cfg.size)
        radius = torch.where(kinds.flat, scale * width * kinds.flat_radius, radius)
        aspect = 2 ** draw.uniform(shape, -1, 1)
        bar = (draw.chance(shape, cfg.bar_probability) & ~kinds.flat) | kinds.thin
        bar_length, bar_width = width * draw.uniform(shape, 0.1, 0.5), draw.uniform(shape, 1.0, 4.0)
        radius_x = torch.where(bar, scale * bar_length, radius * aspect.sqrt())
        radius_y = torch.where(bar, scale * bar_width, radius / aspect.sqrt())
        radius_y = torch.where(kinds.thin, kinds.thin_width / 2, radius_y)  # in output px, not scaled
        angle = draw.uniform(shape, 0, 2 * math.pi)
        round_shape = draw.chance(shape, cfg.round_probability) & ~bar
        sides = torch.where(round_shape, MAX_SIDES, draw.integers(shape, 3, 8))
        sides = torch.where(bar, 4, sides)
        star = draw.chance(shape, cfg.star_probability) & ~round_shape & ~bar
        radii = torch.where(star[..., None], draw.uniform((*shape, MAX_SIDES), 0.35, 1.0), 1.0)
        radii = torch.where(bar[..., None], math.sqrt(2), radii)  # square corners at (+-1, +-1)
        phase = torch.where(bar, math.pi / 4, draw.uniform(shape, 0, 2 * math.pi))
        hole = torch.stack(
            [
                draw.uniform(shape, -0.3, 0.3),
                draw.uniform(shape, -0.3, 0.3),
                draw.uniform(shape, 0.15, 0.5),
                draw.uniform(shape, 0.15, 0.5),
            ],
            dim=-1,
        )
        has_hole = draw.chance(shape, cfg.hole_probability) & ~bar
        surface_count = draw.integers((batch_size, 1), cfg.min_surfaces, cfg.surfaces)
        present = torch.arange(shape[1], device=draw.device) <= surface_count  # and the background

        # The background (surface 0) is centred on the frame and covers everything.
        centre_x[:, 0], centre_y[:, 0] = (width - 1) / 2, (height - 1) / 2
        extent = torch.maximum(radius_x, radius_y) * radii.amax(-1)  # shape within this of its centre
        extent[:, 0] = math.hypot(width, height) / 2
        layout = cfg.road_probability > 0 or cfg.room_probability > 0
        road = Road.draw(batch_size, max_disparity, cfg, draw) if layout else None
        if road is not None:  # the ground (surface 1) covers the whole plane, as the background does
            centre_x[:, 1] = torch.where(road.present, centre_x[:, 0], centre_x[:, 1])
            centre_y[:, 1] = torch.where(road.present, centre_y[:, 0], centre_y[:, 1])
            extent[:, 1] = torch.where(road.present, extent[:, 0], extent[:, 1])
            has_hole[:, 1] &= ~road.present
        cos, sin = torch.cos(angle), torch.sin(angle)
        to_shape = _affine(
            torch.stack(
                [torch.stack([cos / radius_x, sin / radius_x], -1), torch.stack([-sin / radius_y, cos / radius_y], -1)],
                -2,
            ),
            centre_x,
            centre_y,
        )
        to_shape[:, 0] = 0.0
        if road is not None:
            to_shape[:, 1] = torch.where(road.present[:, None, None], 0.0, to_shape[:, 1])
        has_hole[:, 0] = False
        shapes = _Shapes(centre_x, centre_y, extent, to_shape, sides, phase, radii, hole, has_hole, present)
        return shapes, road


def _disparity_planes(
    shapes: _Shapes,
    road: Road | None,
    kinds: SurfaceKinds,
    scene_max: float | torch.Tensor,
    cfg: SceneConfig,
    draw: Draw,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Each surface's disparity (`Scene.plane`, `Scene.curvature`), under each scene's largest
    disparity max (`scene_max` px: one number, or (B,)): the background spans at most
    [0, background_max_fraction * max], the foreground surfaces at most [the background's lowest
    disparity, max] (in road scenes, from the ground under them), thin ones the nearer half of
    [the background's highest disparity (or the ground's), max]; curved ones keep room for their
    bulge; flat ones stay planes."""
    max_disparity = scene_max[:, None] if isinstance(scene_max, torch.Tensor) else scene_max  # (B, 1) or a number
    centre_x, centre_y, extent = shapes.centre_x, shapes.centre_y, shapes.extent
    shape = (extent.shape[0], extent.shape[1])
    gradient = torch.where(draw.chance(shape, cfg.slant_probability), draw.uniform(shape, 0, cfg.max_slope), 0.0)
    gradient_angle = draw.uniform(shape, 0, 2 * math.pi)
    position = draw.uniform(shape, 0, 1)
    curve = _Curve.draw(shape, cfg, draw) if cfg.curve_probability > 0 else None
    background_low = torch.zeros(shape[0], 1, device=draw.device)
    background_gradient, background_disparity = _fit_plane(
        gradient[:, :1],
        extent[:, :1],
        position[:, :1],
        background_low,
        background_low + cfg.background_max_fraction * max_disparity,
    )
    foreground_low = background_disparity - background_gradient * extent[:, :1]
    if road is not None:  # things stand on the ground (nearer than it at their centre row), before the sky or wall
        on_ground = road.disparity(centre_x[:, 1:], centre_y[:, 1:]).clamp_min(0).clamp_max(0.9 * max_disparity)
        on_ground = torch.maximum(on_ground, road.planes[:, 0, 2:])
        foreground_low = torch.where(road.present[:, None], on_ground, foreground_low)
    foreground_high = torch.zeros_like(foreground_low) + max_disparity
    if cfg.thin_probability > 0:  # thin structures: the nearer half of [what is behind them, max]
        behind = background_disparity + background_gradient * extent[:, :1]  # the background's nearest point
        if road is not None:
            behind = torch.where(road.present[:, None], foreground_low, behind)  # the ground under them
        foreground_low = torch.where(kinds.thin[:, 1:], (behind + foreground_high) / 2, foreground_low)
    bulge = torch.zeros_like(gradient[:, 1:])  # px: the curved term's reach within the shape
    if curve is not None:  # room for the bulge: less slope for the plane, a narrower span
        if road is not None:
            curve.present[:, 1] &= ~road.present  # the ground stays a plane
        curve.present &= ~kinds.flat
        bulge = curve.bulge(extent[:, 1:], foreground_high - foreground_low, cfg.max_slope)
        gradient[:, 1:] = torch.minimum(gradient[:, 1:], cfg.max_slope - 2 * bulge / extent[:, 1:])
    foreground_gradient, foreground_disparity = _fit_plane(
        gradient[:, 1:],
        extent[:, 1:],
        position[:, 1:],
        foreground_low + bulge,
        foreground_high - bulge,
    )
    gradient = torch.cat([background_gradient, foreground_gradient], dim=1)
    centre_disparity = torch.cat([background_disparity, foreground_disparity], dim=1)
    slope_x, slope_y = gradient * torch.cos(gradient_angle), gradient * torch.sin(gradient_angle)
    plane = torch.stack([slope_x, slope_y, centre_disparity - slope_x * centre_x - slope_y * centre_y], dim=-1)
    if road is not None:
        plane[:, :2] = torch.where(road.present[:, None, None], road.planes, plane[:, :2])
    curvature = torch.zeros((*shape, 3), device=draw.device)
    if curve is not None:
        curvature[:, 1:] = curve.curvature(bulge, extent[:, 1:])
    return plane, curvature


@dataclass
class _Appearance:
    """What each surface shows (see `Scene`): its texture and how it is mapped, its colour,
    contrast and shading ramp, and the farther scene it reflects."""

    texture: torch.Tensor
    to_texture: torch.Tensor
    projective: torch.Tensor
    fade_disparity: torch.Tensor
    base: torch.Tensor
    contrast: torch.Tensor
    ramp: torch.Tensor
    reflection: torch.Tensor
    reflection_depth: torch.Tensor
    reflection_texture: torch.Tensor
    to_reflection: torch.Tensor

    @staticmethod
    def draw(
        shapes: _Shapes, road: Road | None, scale: torch.Tensor, kinds: SurfaceKinds, cfg: SceneConfig, draw: Draw
    ) -> _Appearance:
        """The look of each surface; flat and repetitive ones (`kinds`) as `SurfaceKinds` says."""
        centre_x, centre_y, extent = shapes.centre_x, shapes.centre_y, shapes.extent
        shape = (extent.shape[0], extent.shape[1])
        texel = scale * draw.log_uniform(shape, *cfg.texel_size)  # output px per texel
        repetitive_texel = kinds.repetitive_period / repetitive_period_texels(cfg.texture_size)
        texel = torch.where(kinds.repetitive, repetitive_texel, texel)
        texture_angle = draw.uniform(shape, 0, 2 * math.pi)
        texture_angle = torch.where(kinds.repetitive, kinds.repetitive_tilt, texture_angle)  # the pattern's u along x
        to_texture = _texture_map(texel, texture_angle, centre_x, centre_y, cfg, draw)
        projective = torch.zeros(shape, dtype=torch.bool, device=draw.device)
        fade_disparity = torch.zeros(shape, device=draw.device)
        grey = draw.uniform((*shape, 1), 20, 235)
        base = grey + draw.uniform((*shape, 3), -30, 30)
        contrast = torch.where(kinds.flat, kinds.flat_contrast, draw.log_uniform(shape, *cfg.contrast))
        ramp_angle = draw.uniform(shape, 0, 2 * math.pi)
        ramp_size = draw.uniform(shape, -cfg.shading, cfg.shading) / (2 * extent)
        ramp_size = torch.where(kinds.flat, kinds.flat_shading / (2 * extent), ramp_size)
        ramp_x, ramp_y = ramp_size * torch.cos(ramp_angle), ramp_size * torch.sin(ramp_angle)
        ramp = torch.stack([ramp_x, ramp_y, -ramp_x * centre_x - ramp_y * centre_y], dim=-1)
        texture = draw.integers(shape, 0, cfg.texture_count - 1)
        texture = torch.where(kinds.repetitive, cfg.texture_count + kinds.repetitive_texture, texture)
        reflection_texture, to_reflection = torch.zeros_like(texture), torch.zeros_like(to_texture)
        if cfg.reflective_probability > 0:  # another texture of the bank, mapped as a surface's own is
            reflection_texture = draw.integers(shape, 0, cfg.texture_count - 1)
            reflection_texel = scale * draw.log_uniform(shape, *cfg.texel_size)
            reflection_angle = draw.uniform(shape, 0, 2 * math.pi)
            to_reflection = _texture_map(reflection_texel, reflection_angle, centre_x, centre_y, cfg, draw)
        reflection = torch.where(kinds.reflective, kinds.reflection_contrast, 0.0)
        if road is not None:
            to_texture[:, 1] = torch.where(road.present[:, None, None], road.to_texture, to_texture[:, 1])
            projective[:, 1] = road.present
            fade_disparity[:, 1] = road.fade_disparity
            contrast[:, 0] = torch.where(road.sky, road.sky_contrast, contrast[:, 0])
        return _Appearance(
            texture,
            to_texture,
            projective,
            fade_disparity,
            base,
            contrast,
            ramp,
            reflection,
            kinds.reflection_depth,
            reflection_texture,
            to_reflection,
        )


@dataclass
class _Lighting:
    """A scene's light and its surfaces' gloss (see `SceneConfig` and `Scene`)."""

    light: torch.Tensor
    ambient: torch.Tensor
    relief: torch.Tensor
    camera: torch.Tensor
    specular: torch.Tensor
    shininess: torch.Tensor

    @staticmethod
    def none(shape: tuple[int, int], cfg: SceneConfig, draw: Draw) -> _Lighting:
        """No light: every surface shows its own colour (ambient 1), no highlights."""
        batch = shape[0]
        light = torch.zeros(batch, 3, device=draw.device)
        light[:, 2] = -1.0
        ones, zeros = torch.ones(batch, device=draw.device), torch.zeros(shape, device=draw.device)
        camera = torch.tensor([cfg.width, (cfg.width - 1) / 2, (cfg.height - 1) / 2], device=draw.device)
        return _Lighting(light, ones, ones, camera.expand(batch, 3), zeros, zeros + 1)

    @staticmethod
    def draw(shape: tuple[int, int], cfg: SceneConfig, draw: Draw) -> _Lighting:
        batch = shape[0]
        lit = draw.chance((batch,), cfg.lighting_probability)
        sideways = draw.uniform((batch, 2), -1.5, 1.5)  # the light comes from the camera's side
        light = torch.cat([sideways, -torch.ones(batch, 1, device=draw.device)], dim=1)
        light = light / light.norm(dim=1, keepdim=True)
        ambient = torch.where(lit, draw.uniform((batch,), 0.25, 0.8), 1.0)
        relief = draw.log_uniform((batch,), 0.5, 4.0)
        focal = cfg.width * draw.log_uniform((batch,), 0.7, 2.0)
        centre = torch.tensor([(cfg.width - 1) / 2, (cfg.height - 1) / 2], device=draw.device).expand(batch, 2)
        glossy = draw.chance(shape, cfg.specular_probability) & lit[:, None]
        specular = torch.where(glossy, draw.uniform(shape, 40.0, 200.0), 0.0)
        shininess = draw.log_uniform(shape, 20.0, 200.0)
        return _Lighting(light, ambient, relief, torch.cat([focal[:, None], centre], 1), specular, shininess)


@dataclass
class _Curve:
    """The quadratic terms of curved surfaces (see `SceneConfig`), drawn for every slot (B, S); the
    background (slot 0) stays planar.

    present: (B, S) bool, which surfaces are curved.
    fraction: (B, S) in [0, 1], the share of the available room the bulge takes.
    principal: (B, S, 2) in [-1, 1], (l1, l2), the relative curvatures along the two axes.
    axis: (B, S) radians, the direction of the first axis.
    """

    present: torch.Tensor
    fraction: torch.Tensor
    principal: torch.Tensor
    axis: torch.Tensor

    @staticmethod
    def draw(shape: tuple[int, int], cfg: SceneConfig, draw: Draw) -> _Curve:
        present = draw.chance(shape, cfg.curve_probability)
        present[:, 0] = False
        return _Curve(
            present=present,
            fraction=draw.uniform(shape, 0, 1),
            principal=draw.uniform((*shape, 2), -1, 1),
            axis=draw.uniform(shape, 0, math.pi),
        )

    def bulge(self, extent: torch.Tensor, span: torch.Tensor, max_slope: float) -> torch.Tensor:
        """(B, S - 1) px, the foreground's bulges delta: |the quadratic term| <= delta and its slope
        <= 2 * delta / extent within the shape; delta takes at most all the slope budget and a
        quarter of the disparity span (B, S - 1) px, so that a plane still fits beside it."""
        room = torch.minimum(max_slope * extent / 2, span / 4)
        return torch.where(self.present[:, 1:], self.fraction[:, 1:] * room, 0.0)

    def curvature(self, bulge: torch.Tensor, extent: torch.Tensor) -> torch.Tensor:
        """(B, S - 1, 3) (kxx, kxy, kyy) px^-1 of the foreground: delta * (l1*p1^2 + l2*p2^2) / R^2."""
        l1, l2 = (part[:, 1:] for part in self.principal.unbind(-1))
        cos, sin = torch.cos(self.axis[:, 1:]), torch.sin(self.axis[:, 1:])
        scale = bulge / extent.square()
        return scale[..., None] * torch.stack(
            [l1 * cos * cos + l2 * sin * sin, 2 * (l1 - l2) * cos * sin, l1 * sin * sin + l2 * cos * cos], dim=-1
        )


def _fit_plane(
    gradient: torch.Tensor,
    extent: torch.Tensor,
    position: torch.Tensor,
    low: torch.Tensor,
    high: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Fit planes into disparity spans: returns (gradient, centre disparity), each (B, n).

    A surface reaching ``extent`` px from its centre keeps its disparity in [low, high] (B, 1) when
    gradient <= (high - low) / (2 * extent); larger gradients are reduced to that. ``position`` in
    [0, 1] places the centre disparity within what remains of the span.
    """
    gradient = torch.minimum(gradient, (high - low) / (2 * extent))
    reach = gradient * extent
    return gradient, low + reach + position * (high - low - 2 * reach)


def _texture_map(
    texel: torch.Tensor,
    angle: torch.Tensor,
    centre_x: torch.Tensor,
    centre_y: torch.Tensor,
    cfg: SceneConfig,
    draw: Draw,
) -> torch.Tensor:
    """(B, S, 2, 3) affine maps from (x, y) px to texel coordinates: `texel` px per texel, the
    texture's u axis turned by `angle` radians, about each surface's centre, at a random place of
    the (wrapping) texture; each (B, S)."""
    cos, sin = torch.cos(angle) / texel, torch.sin(angle) / texel
    to_texture = _affine(
        torch.stack([torch.stack([cos, sin], -1), torch.stack([-sin, cos], -1)], -2), centre_x, centre_y
    )
    to_texture[..., 2] += draw.uniform((*texel.shape, 2), 0, cfg.texture_size)
    return to_texture


def _affine(linear: torch.Tensor, centre_x: torch.Tensor, centre_y: torch.Tensor) -> torch.Tensor:
    """(..., 2, 3) affine map p -> linear @ (p - centre), from (..., 2, 2) and (...) centres."""
    centre = torch.stack([centre_x, centre_y], dim=-1)[..., None]
    return torch.cat([linear, -(linear @ centre)], dim=-1)
