"""Procedural rectified stereo scenes with exact ground truth, rendered with torch on any device.

A scene is a background plane plus many foreground surfaces. Each surface is a patch of disparity
``d(x, y) = a*x + b*y + c`` (slanted or fronto-parallel), optionally curved by a quadratic term
(``curve_probability``: domes, bowls, saddles, cylinders), cut to a random shape (star polygon:
triangles to 8-gons and stars, near-ellipses, thin bars; optionally with an elliptic hole) and
painted with a texture attached to the surface (options aimed at hard cases: thin structures, flat
planes, repetitive patterns, wide disparity ranges, drawn in `stereo_data.hard_cases`). Both views
are rendered exactly: in each view, every pixel shows the surface with the largest disparity there
(z-buffer). A right pixel ``x_r`` sees surface S at the left coordinate ``x_l`` solving
``x_l - d_S(x_l, y) = x_r`` (for a plane ``x_l = (x_r + b*y + c) / (1 - a)``; for a curved surface
the root of a quadratic), and shows S's texture at ``(x_l, y)``; so warping the right view by the
left ground truth reproduces the left view wherever the match is visible.

Coordinates: x to the right, y down, in pixels of the output images, pixel centres at integers.
Disparity is positive, in pixels of the LEFT view: left pixel (x, y) matches right pixel (x - d, y).

Randomness comes only from a ``torch.Generator`` on the target device seeded by ``generate``'s
``seed``: a (config, device, batch_size, seed) tuple gives the same batch bit for bit. CPU and CUDA
generators differ, so a seed gives different scenes on different device types.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import reduce

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from .hard_cases import REPETITIVE_TEXTURES, SurfaceKinds, repetitive_period_texels, scene_max_disparity
from .photos import load_photos

__all__ = ["PhotometricConfig", "SceneConfig", "Scene", "SyntheticBatch", "SceneGenerator"]

MAX_SIDES = 24
"""Polygons have 3..MAX_SIDES vertices; a MAX_SIDES-gon with equal radii stands for an ellipse."""
_OCCLUSION_TOLERANCE = 1e-3  # px: a surface must be this much nearer to hide a match


@dataclass(frozen=True)
class PhotometricConfig:
    """Random photometric changes, drawn independently for each view and applied after rendering,
    in this order: Gaussian blur, gamma, vignetting, gain, offset, Gaussian noise, clipping to
    [0, 255], JPEG compression."""

    blur_probability: float = 0.3
    blur_sigma: tuple[float, float] = (0.3, 1.2)  # px
    gamma: tuple[float, float] = (0.75, 1.35)  # out = 255 * (in / 255) ** gamma
    gain: tuple[float, float] = (0.7, 1.3)  # multiplies all channels
    channel_gain: tuple[float, float] = (0.9, 1.1)  # multiplies each channel on top of gain
    offset: tuple[float, float] = (-15.0, 15.0)  # grey levels added
    noise_sigma: tuple[float, float] = (0.0, 4.0)  # grey levels, per pixel and channel
    vignetting: float = 0.0  # at most this share of the light lost at the frame's corners (off: 0)
    jpeg_probability: float = 0.0  # views saved as JPEG and read back (compression artefacts)
    jpeg_quality: tuple[int, int] = (40, 95)  # JPEG quality, uniform

    def __post_init__(self) -> None:
        if not 0.0 <= self.vignetting < 1.0:
            raise ValueError(f"vignetting must be in [0, 1), got {self.vignetting}")
        if not 0.0 <= self.jpeg_probability <= 1.0:
            raise ValueError(f"jpeg_probability must be in [0, 1], got {self.jpeg_probability}")
        if not 1 <= self.jpeg_quality[0] <= self.jpeg_quality[1] <= 100:
            raise ValueError(f"jpeg_quality must be 1 <= low <= high <= 100, got {self.jpeg_quality}")


@dataclass(frozen=True)
class SceneConfig:
    """What the generator draws. Lengths are in output pixels unless said otherwise.

    Anti-aliasing: with ``supersample`` k > 1 each pixel's colour is the mean of a k x k grid of
    point samples spread evenly over its area (as a camera integrates light over a pixel): edges get
    partial-coverage pixels and texels finer than a pixel are averaged, not aliased. The ground truth
    (disparity, occlusion) stays the point value at the pixel centre.

    Curved surfaces: with ``curve_probability`` a foreground surface's disparity gets a quadratic
    term about its centre, ``delta * (l1 * p1**2 + l2 * p2**2) / R**2`` with p1, p2 the point's
    coordinates along two random perpendicular axes, R the shape's extent, l1, l2 in [-1, 1] (same
    signs: a dome or a bowl; opposite: a saddle; one near zero: a cylinder) and delta px the bulge.
    The plane's slope and span are shrunk so that the surface still keeps |grad d| <= max_slope and
    its disparity range within the shape.

    Lighting: with ``lighting_probability`` a scene is lit by a directional light: each surface
    point's colour is scaled by ambient + (1 - ambient) * max(0, n . L), its normal n following its
    disparity gradient (so curved surfaces shade smoothly, slanted ones by their slant), the same in
    both views. With ``specular_probability`` surfaces of lit scenes also get a Blinn-Phong highlight
    towards each camera: the right camera sits to the right, so a highlight lies elsewhere on the
    surface in each view (real glossy surfaces break matching so). The ground truth is unchanged.

    Road scenes: with ``road_probability`` a scene is laid out as driving scenes are: a ground plane
    receding to a horizon (a strong vertical disparity gradient), a far and weakly textured sky
    above it, and the foreground surfaces standing on the ground (each at least as near as the
    ground at its centre row); the ground's texture is seen in perspective (see `_Road`).

    Room scenes: with ``room_probability`` a scene is laid out as indoor scenes are: a back wall
    (fronto-parallel, at 10-45 % of the maximum disparity, textured as any surface) and a floor
    meeting it along a line a quarter to nine tenths down the frame, nearing the camera below it;
    the floor's texture is seen in perspective as a road's ground is, and the foreground surfaces
    stand on the floor in front of the wall.

    Hard cases (`stereo_data.hard_cases` has their ranges), each off at 0:
    - ``thin_probability``: foreground surfaces that are thin structures (wires, stems, pipes, chair
      legs): bars 1-6 px wide and 0.2-1 frame widths long, often crossing, with their disparity in the
      nearer half of [the background's highest, max_disparity]: in front of the background by at
      least (1 - background_max_fraction) / 2 of the largest disparity (in road and room scenes: of
      the ground under their centre).
    - ``flat_probability``: surfaces (of those not thin; the background too) that are large weakly
      textured planes (walls, tables, floors): 0.5-1 frame widths across, texture std 1-4 grey
      levels, a brightness ramp of a third to all of ``shading`` across them, never curved.
    - ``repetitive_probability``: surfaces (of those not flat) painted with a periodic pattern
      (stripes, checkers, grid lines or dots) of period 4-40 px repeating along the rows (turned by
      at most 10 degrees): ambiguous matches one period apart.
    - ``wide_range_probability``: scenes whose largest disparity is drawn uniformly in
      [max_disparity, wide_max_disparity] instead of max_disparity.

    Scale/crop augmentation: each scene is magnified by a random ``s = 2**U(log2_scale)``: every
    length (shape sizes, bar widths, texel sizes) is its unscaled length times s. A random crop of a
    procedural scene is distributed like the scene itself, so the crop is implicit: shapes are
    spread over the output frame (and a margin of 10 % around it) at every scale. Disparities are
    drawn in output pixels after scaling, so that they span [0, max_disparity] at every scale.
    """

    height: int = 384
    width: int = 512
    max_disparity: float | None = None  # px; None means 192 * width / 512
    wide_max_disparity: float | None = None  # px, wide-range scenes; None means max(max_disparity, 256 * width / 512)
    surfaces: int = 24  # foreground surface slots per scene
    min_surfaces: int = 8  # a scene uses U{min_surfaces..surfaces} of them
    size: tuple[float, float] = (0.02, 0.35)  # unscaled shape radius / width, log-uniform
    bar_probability: float = 0.15  # thin bars: 2-8 px wide, 0.2-1 width long (unscaled)
    round_probability: float = 0.3  # near-ellipses; the others are 3- to 8-gons
    star_probability: float = 0.5  # polygons with random vertex radii (irregular, concave)
    hole_probability: float = 0.2
    slant_probability: float = 0.7  # the others are fronto-parallel
    max_slope: float = 0.4  # bound on |grad d| (px of disparity per px); must be < 1
    background_max_fraction: float = 0.5  # the background's disparity stays below this * max
    texture_size: int = 256  # texels per side of each (periodic) texture
    noise_textures: int = 4  # 1/f^alpha noise: photo-like, fine detail, smooth gradients
    leaves_textures: int = 2  # dead leaves: random discs with sharp edges, scale invariant
    pattern_textures: int = 2  # stripes, checkers, grids, dots
    photo_textures: int = 0  # crops of photographs (stereo_data.photos; needs scikit-image)
    texel_size: tuple[float, float] = (1.2, 5.0)  # unscaled px per texel, log-uniform
    contrast: tuple[float, float] = (6.0, 100.0)  # grey-level std of a surface's texture, log-uniform
    shading: float = 60.0  # at most this many grey levels of linear ramp across a surface
    log2_scale: tuple[float, float] = (-0.2, 0.4)
    curve_probability: float = 0.0  # foreground surfaces that are curved (quadric disparity); the others planar
    lighting_probability: float = 0.0  # scenes lit by a directional light (shading by surface orientation)
    specular_probability: float = 0.0  # surfaces of lit scenes with highlights, which differ between the views
    road_probability: float = 0.0  # scenes laid out as a road under a sky (see `_Road`); the others as before
    room_probability: float = 0.0  # scenes laid out as a room: a floor meeting a back wall (not road scenes)
    thin_probability: float = 0.0  # foreground surfaces that are thin structures near the camera
    flat_probability: float = 0.0  # surfaces that are large weakly textured planes with slow shading
    repetitive_probability: float = 0.0  # surfaces painted with a pattern repeating every 4-40 px along the rows
    wide_range_probability: float = 0.0  # scenes whose largest disparity is drawn up to wide_max_disparity
    supersample: int = 1  # anti-aliasing: images are the mean of supersample x supersample samples per pixel
    photometric: PhotometricConfig | None = field(default_factory=PhotometricConfig)

    def __post_init__(self) -> None:
        max_disparity = 192.0 * self.width / 512.0 if self.max_disparity is None else self.max_disparity
        object.__setattr__(self, "max_disparity", max_disparity)
        wide_max = self.wide_max_disparity
        wide_max = max(max_disparity, 256.0 * self.width / 512.0) if wide_max is None else wide_max
        object.__setattr__(self, "wide_max_disparity", wide_max)
        if self.height < 1 or self.width < 1:
            raise ValueError(f"image size must be positive, got {self.height}x{self.width}")
        if not 0 < max_disparity:
            raise ValueError(f"max_disparity must be positive, got {max_disparity}")
        if self.wide_range_probability > 0 and not wide_max >= max_disparity:
            raise ValueError(f"wide_max_disparity must be at least max_disparity, got {wide_max}")
        if not 0 <= self.max_slope < 1:
            raise ValueError("max_slope must be in [0, 1): the right view needs 1 - a > 0")
        if not 1 <= self.min_surfaces <= self.surfaces:
            raise ValueError("need 1 <= min_surfaces <= surfaces")
        if any(low > high for low, high in (self.log2_scale, self.size, self.texel_size)):
            raise ValueError("ranges must be (low, high)")
        if self.texture_count < 1:
            raise ValueError("need at least one texture")
        for name in (
            "road_probability",
            "room_probability",
            "curve_probability",
            "lighting_probability",
            "specular_probability",
            "thin_probability",
            "flat_probability",
            "repetitive_probability",
            "wide_range_probability",
        ):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if self.supersample < 1:
            raise ValueError(f"supersample must be a positive integer, got {self.supersample}")
        if 2 ** self.log2_scale[0] * self.texel_size[0] * self.supersample < 1:
            raise ValueError("the smallest texel must cover at least one sample: 1 / supersample px (aliasing)")

    @property
    def texture_count(self) -> int:
        return self.noise_textures + self.leaves_textures + self.pattern_textures + self.photo_textures


@dataclass
class Scene:
    """B scenes of S surfaces each, in output pixel coordinates of the left view.

    A surface is the set of points (x, y) whose shape-frame coordinates (u, v) = to_shape @ (x, y, 1)
    lie in its star polygon and not in its hole. The polygon has ``sides`` vertices, vertex j at
    angle ``phase + 2*pi*j/sides`` and distance ``radii[j]`` from (0, 0). A surface with a zero
    ``to_shape`` covers the whole plane (the background, surface 0 in generated scenes).

    plane: (B, S, 3) float, (a, b, c): the surface's disparity is a*x + b*y + c px (a < 1), plus
        the quadratic term of ``curvature`` (see `surface_disparity`).
    curvature: (B, S, 3) float, (kxx, kxy, kyy) px of disparity per px^2: the term
        kxx*u^2 + kxy*u*v + kyy*v^2 with (u, v) = (x, y) - apex; zero for planar surfaces.
    apex: (B, S, 2) float, (x, y) px, the origin of the quadratic term.
    to_shape: (B, S, 2, 3) float, affine map from (x, y) px to the shape frame.
    sides: (B, S) int64 in [3, MAX_SIDES].
    phase: (B, S) float, radians.
    radii: (B, S, MAX_SIDES) float > 0, shape-frame units; entries >= sides are ignored.
    hole: (B, S, 4) float, (u0, v0, ru, rv): the ellipse ((u-u0)/ru)^2 + ((v-v0)/rv)^2 < 1, ru, rv > 0.
    has_hole: (B, S) bool.
    present: (B, S) bool; absent surfaces are never drawn.
    texture: (B, S) int64, which of the scene's K textures the surface shows.
    to_texture: (B, S, 2, 3) float, affine map from (x, y) px to texel coordinates (wrapping); for a
        ``projective`` surface the texel coordinates are that map divided by the surface's
        disparity, which is a texture fixed to the plane seen in perspective.
    projective: (B, S) bool.
    fade_disparity: (B, S) float px, projective surfaces only: where their disparity falls below
        twice this the texture fades out (it would be finer than a sample), to nothing at this.
    base: (B, S, 3) float, mean RGB colour, grey levels.
    contrast: (B, S) float, grey levels per unit of (standardised) texture.
    ramp: (B, S, 3) float, (gx, gy, g0): gx*x + gy*y + g0 grey levels are added (shading).
    specular: (B, S) float grey levels of a full highlight (0: matte); shininess: (B, S) its
        Blinn-Phong exponent.
    light: (B, 3) float, unit vector from the surfaces towards the light (camera frame: x right,
        y down, z forward); ambient: (B,) in (0, 1], the unlit share (1: no lighting); relief: (B,)
        the normal's tilt per unit of disparity gradient, n = normalize(-relief * grad d, -1);
        camera: (B, 3) (f, cx, cy) px, the pinhole that gives each pixel its direction to the
        camera: a point seen at x in a view sees that camera along (-(x - cx) / f, -(y - cy) / f, -1).
    textures: (B, K, T, T, 3) float, the texture bank: periodic, zero mean, unit std per texture.
    """

    plane: torch.Tensor
    curvature: torch.Tensor
    apex: torch.Tensor
    to_shape: torch.Tensor
    sides: torch.Tensor
    phase: torch.Tensor
    radii: torch.Tensor
    hole: torch.Tensor
    has_hole: torch.Tensor
    present: torch.Tensor
    texture: torch.Tensor
    to_texture: torch.Tensor
    projective: torch.Tensor
    fade_disparity: torch.Tensor
    base: torch.Tensor
    contrast: torch.Tensor
    ramp: torch.Tensor
    specular: torch.Tensor
    shininess: torch.Tensor
    light: torch.Tensor
    ambient: torch.Tensor
    relief: torch.Tensor
    camera: torch.Tensor
    textures: torch.Tensor

    def translated(self, dx: float, dy: float) -> Scene:
        """The scene seen by a camera panned by (dx, dy) px: each view of the result at (x, y) is
        this scene's at (x + dx, y + dy), disparities included (a static scene in a video whose
        camera moves sideways: content moves by (-dx, -dy) px per frame)."""

        def shifted(affine: torch.Tensor) -> torch.Tensor:  # (..., k) maps of (x, y, 1), k = 3
            moved = affine.clone()
            moved[..., 2] += affine[..., 0] * dx + affine[..., 1] * dy
            return moved

        offset = torch.tensor([dx, dy], dtype=self.apex.dtype, device=self.apex.device)
        return replace(
            self,
            plane=shifted(self.plane),
            apex=self.apex - offset,
            to_shape=shifted(self.to_shape),
            to_texture=shifted(self.to_texture),
            ramp=shifted(self.ramp),
        )

    def surfaces(self, part: slice) -> Scene:
        """The same scenes with only the surfaces ``part`` (sharing the per-scene values)."""
        fields = vars(self).items()
        return Scene(**{name: v if name in _PER_SCENE else v[:, part] for name, v in fields})


_PER_SCENE = frozenset({"textures", "light", "ambient", "relief", "camera"})
"""`Scene` fields of the whole scene, not of each surface."""


@dataclass
class SyntheticBatch:
    """A batch of rendered pairs.

    left, right: (B, 3, H, W) float32 RGB in [0, 255].
    disparity: (B, 1, H, W) float32 px of the LEFT view, in [0, max_disparity] (wide-range scenes:
        [0, wide_max_disparity]); left pixel (x, y) matches right pixel (x - d, y). Dense and exact,
        occluded pixels included.
    valid: (B, 1, H, W) bool, where the ground truth is defined: everywhere (kept for the contract
        shared with real datasets).
    occluded: (B, 1, H, W) bool, left pixels whose match is hidden by a nearer surface in the right
        view, or out of its frame (x - d < 0).
    """

    left: torch.Tensor
    right: torch.Tensor
    disparity: torch.Tensor
    valid: torch.Tensor
    occluded: torch.Tensor

    def pair(self, index: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Pair `index` as images: (left, right) uint8 HxWx3 RGB, on the host."""
        left, right = (
            view[index].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).cpu().numpy()
            for view in (self.left, self.right)
        )
        return left, right


class _Draw:
    """Random tensors on one device from one generator (the only source of randomness)."""

    def __init__(self, generator: torch.Generator, device: torch.device) -> None:
        self.generator = generator
        self.device = device

    def uniform(self, shape: tuple[int, ...], low: float, high: float | torch.Tensor) -> torch.Tensor:
        sample = torch.rand(shape, generator=self.generator, device=self.device)
        return low + (high - low) * sample

    def log_uniform(self, shape: tuple[int, ...], low: float, high: float) -> torch.Tensor:
        return torch.exp(self.uniform(shape, math.log(low), math.log(high)))

    def normal(self, shape: tuple[int, ...]) -> torch.Tensor:
        return torch.randn(shape, generator=self.generator, device=self.device)

    def chance(self, shape: tuple[int, ...], probability: float) -> torch.Tensor:
        return self.uniform(shape, 0.0, 1.0) < probability

    def integers(self, shape: tuple[int, ...], low: int, high: int) -> torch.Tensor:
        """Uniform int64 in [low, high]."""
        return torch.randint(low, high + 1, shape, generator=self.generator, device=self.device)


class SceneGenerator:
    """Draws and renders batches of procedural stereo scenes on ``device``."""

    def __init__(self, config: SceneConfig, device: str | torch.device = "cpu") -> None:
        self.config = config
        self.device = torch.device(device)
        self._x = torch.arange(config.width, device=self.device, dtype=torch.float32).view(1, 1, 1, -1)
        self._y = torch.arange(config.height, device=self.device, dtype=torch.float32).view(1, 1, -1, 1)
        self._photos = load_photos(config.texture_size, self.device) if config.photo_textures else []

    def generate(self, batch_size: int, seed: int) -> SyntheticBatch:
        """Draw, render and (if configured) photometrically augment ``batch_size`` pairs."""
        draw = _Draw(torch.Generator(device=self.device).manual_seed(seed), self.device)
        batch = self.render(self._sample_scene(batch_size, draw))
        if self.config.photometric is not None:
            batch.left = _photometric(batch.left, self.config.photometric, draw)
            batch.right = _photometric(batch.right, self.config.photometric, draw)
        return batch

    def pan(self, seed: int, frames: int, step: tuple[float, float]) -> list[SyntheticBatch]:
        """A video with exact ground truth: `frames` renders (batches of one, without photometric
        changes) of one static scene seen by a camera panning `step` (dx, dy) px per frame."""
        scene = self.sample_scene(batch_size=1, seed=seed)
        return [self.render(scene.translated(step[0] * t, step[1] * t)) for t in range(frames)]

    def sample_scene(self, batch_size: int, seed: int) -> Scene:
        """The scenes that ``generate(batch_size, seed)`` renders."""
        draw = _Draw(torch.Generator(device=self.device).manual_seed(seed), self.device)
        return self._sample_scene(batch_size, draw)

    def render(self, scene: Scene) -> SyntheticBatch:
        """Render both views of ``scene`` exactly, without photometric changes."""
        x, y = self._x, self._y
        left_disparity, left_surface, _ = _nearest_surface(scene, x, y, "left")
        if self.config.supersample == 1:  # the point samples are the pixel centres: shade what was found
            left = _shade(scene, left_surface, x.expand_as(left_disparity), y, "left")
        else:
            left = self._view(scene, "left")
        right = self._view(scene, "right")
        x_match = x - left_disparity
        match_disparity, _, _ = _nearest_surface(scene, x_match, y, "right")
        occluded = (match_disparity > left_disparity + _OCCLUSION_TOLERANCE) | (x_match < 0)
        return SyntheticBatch(
            left=left,
            right=right,
            disparity=left_disparity,
            valid=torch.ones_like(occluded),
            occluded=occluded,
        )

    def _view(self, scene: Scene, view: str) -> torch.Tensor:
        """(B, 3, H, W) colour of one view ("left" or "right"): the mean of its k x k samples per
        pixel (k = supersample), at offsets (i + 1/2) / k - 1/2 px from the pixel centre."""
        k = self.config.supersample
        offsets = (torch.arange(k, device=self.device, dtype=torch.float32) + 0.5) / k - 0.5
        x = (self._x[..., None] + offsets).flatten(-2)  # (1, 1, 1, W * k), sample columns
        y = (self._y[..., None, :] + offsets[:, None]).flatten(-3, -2)  # (1, 1, H * k, 1), sample rows
        _, surface, x_left = _nearest_surface(scene, x, y, view)
        color = _shade(scene, surface, x_left.expand_as(surface), y, view)
        return F.avg_pool2d(color, k) if k > 1 else color

    def _sample_scene(self, batch_size: int, draw: _Draw) -> Scene:
        cfg = self.config
        shape = (batch_size, cfg.surfaces + 1)  # surface 0 is the background
        scale = 2 ** draw.uniform((batch_size, 1), *cfg.log2_scale)  # magnification s
        kinds = SurfaceKinds.draw(shape, cfg, draw)
        max_disparity = scene_max_disparity(batch_size, cfg, draw)
        shapes, road = _Shapes.draw(shape, scale, kinds, max_disparity, cfg, draw)
        plane, curvature = _disparity_planes(shapes, road, kinds, max_disparity, cfg, draw)
        look = _Appearance.draw(shapes, road, scale, kinds, cfg, draw)
        lighting = (
            _Lighting.draw(shape, cfg, draw) if cfg.lighting_probability > 0 else _Lighting.none(shape, cfg, draw)
        )
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
            specular=lighting.specular,
            shininess=lighting.shininess,
            light=lighting.light,
            ambient=lighting.ambient,
            relief=lighting.relief,
            camera=lighting.camera,
            textures=_texture_bank(batch_size, cfg, draw, self._photos),
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
        draw: _Draw,
    ) -> tuple[_Shapes, _Road | None]:
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
        road = _Road.draw(batch_size, max_disparity, cfg, draw) if layout else None
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
    road: _Road | None,
    kinds: SurfaceKinds,
    scene_max: float | torch.Tensor,
    cfg: SceneConfig,
    draw: _Draw,
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
    contrast and shading ramp."""

    texture: torch.Tensor
    to_texture: torch.Tensor
    projective: torch.Tensor
    fade_disparity: torch.Tensor
    base: torch.Tensor
    contrast: torch.Tensor
    ramp: torch.Tensor

    @staticmethod
    def draw(
        shapes: _Shapes, road: _Road | None, scale: torch.Tensor, kinds: SurfaceKinds, cfg: SceneConfig, draw: _Draw
    ) -> _Appearance:
        """The look of each surface; flat and repetitive ones (`kinds`) as `SurfaceKinds` says."""
        centre_x, centre_y, extent = shapes.centre_x, shapes.centre_y, shapes.extent
        shape = (extent.shape[0], extent.shape[1])
        texel = scale * draw.log_uniform(shape, *cfg.texel_size)  # output px per texel
        repetitive_texel = kinds.repetitive_period / repetitive_period_texels(cfg.texture_size)
        texel = torch.where(kinds.repetitive, repetitive_texel, texel)
        texture_angle = draw.uniform(shape, 0, 2 * math.pi)
        texture_angle = torch.where(kinds.repetitive, kinds.repetitive_tilt, texture_angle)  # the pattern's u along x
        cos, sin = torch.cos(texture_angle) / texel, torch.sin(texture_angle) / texel
        to_texture = _affine(
            torch.stack([torch.stack([cos, sin], -1), torch.stack([-sin, cos], -1)], -2),
            centre_x,
            centre_y,
        )
        to_texture[..., 2] += draw.uniform((*shape, 2), 0, cfg.texture_size)
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
        if road is not None:
            to_texture[:, 1] = torch.where(road.present[:, None, None], road.to_texture, to_texture[:, 1])
            projective[:, 1] = road.present
            fade_disparity[:, 1] = road.fade_disparity
            contrast[:, 0] = torch.where(road.sky, road.sky_contrast, contrast[:, 0])
        return _Appearance(texture, to_texture, projective, fade_disparity, base, contrast, ramp)


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
    def none(shape: tuple[int, int], cfg: SceneConfig, draw: _Draw) -> _Lighting:
        """No light: every surface shows its own colour (ambient 1), no highlights."""
        batch = shape[0]
        light = torch.zeros(batch, 3, device=draw.device)
        light[:, 2] = -1.0
        ones, zeros = torch.ones(batch, device=draw.device), torch.zeros(shape, device=draw.device)
        camera = torch.tensor([cfg.width, (cfg.width - 1) / 2, (cfg.height - 1) / 2], device=draw.device)
        return _Lighting(light, ones, ones, camera.expand(batch, 3), zeros, zeros + 1)

    @staticmethod
    def draw(shape: tuple[int, int], cfg: SceneConfig, draw: _Draw) -> _Lighting:
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
    def draw(shape: tuple[int, int], cfg: SceneConfig, draw: _Draw) -> _Curve:
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


@dataclass
class _Road:
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
    def draw(batch_size: int, max_disparity: float | torch.Tensor, cfg: SceneConfig, draw: _Draw) -> _Road:
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
        return _Road(present, sky, torch.stack([background, ground], dim=1), to_texture, fade, sky_contrast)

    def disparity(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """The ground's disparity (px) at points x, y (B, n) px; negative above the horizon."""
        a, b, c = self.planes[:, 1, :, None].unbind(1)
        return a * x + b * y + c


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


def _affine(linear: torch.Tensor, centre_x: torch.Tensor, centre_y: torch.Tensor) -> torch.Tensor:
    """(..., 2, 3) affine map p -> linear @ (p - centre), from (..., 2, 2) and (...) centres."""
    centre = torch.stack([centre_x, centre_y], dim=-1)[..., None]
    return torch.cat([linear, -(linear @ centre)], dim=-1)


def _apply(affine: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Apply (B, S, 2, 3) affine maps to points: x broadcastable to (B, S, H, W), y (1, 1, H, 1)."""
    m = affine[..., None, None]  # (B, S, 2, 3, 1, 1)
    u, v = (m[:, :, row, 0] * x + (m[:, :, row, 1] * y + m[:, :, row, 2]) for row in (0, 1))
    return u, v


def _surface_disparity(
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


def _surface_gradient(
    plane: torch.Tensor, curvature: torch.Tensor, apex: torch.Tensor, x: torch.Tensor, y: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """(d_x, d_y): the gradient of `_surface_disparity` (px per px) at the same points."""
    kxx, kxy, kyy = curvature.unbind(-1)
    u, v = x - apex[..., 0], y - apex[..., 1]
    return plane[..., 0] + 2 * kxx * u + kxy * v, plane[..., 1] + kxy * u + 2 * kyy * v


def _seen_from_right(scene: Scene, x_right: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
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


def _nearest_surface(
    scene: Scene, x: torch.Tensor, y: torch.Tensor, view: str
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The nearest surface at each query point of one view (z-buffer: the largest disparity wins).

    x: query x in the ``view`` ("left" or "right") image, px: (1, 1, 1, W) columns shared by
        every row (a view's sample grid, ascending), or (B, 1, H, W) one per point.
    y: (1, 1, H, 1) rows, px, ascending.
    Returns the winner's disparity (B, 1, H, W) px, its index (B, 1, H, W) int64, and the left-view
    x of the winner's point (B, 1, H, W) px. Each surface is evaluated only on the rows (and, for
    shared columns, the columns) its bounding box in the view can reach (`_view_bounds`); ties go
    to the lowest index.
    """
    batch, surfaces = scene.sides.shape
    shape = (batch, 1, y.shape[-2], x.shape[-1])
    nearest = torch.full(shape, -math.inf, dtype=x.dtype, device=x.device)
    index = torch.zeros(shape, dtype=torch.int64, device=x.device)
    x_nearest = x.expand(shape).clone()
    low_x, high_x, low_y, high_y = _view_bounds(scene, view).unbind(-1)  # (B, S) each
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
        x_left = x_part if view == "left" else _seen_from_right(part, x_part, y_part)
        plane, curvature, apex = (value[:, :, None, None] for value in (part.plane, part.curvature, part.apex))
        disparity = _surface_disparity(plane, curvature, apex, x_left, y_part)
        disparity = torch.where(_covers(part, x_left, y_part), disparity, -math.inf)
        region = (slice(None), slice(None), row, column)
        nearer = disparity > nearest[region]
        nearest[region] = torch.where(nearer, disparity, nearest[region])
        index[region] = index[region].masked_fill(nearer, surface)
        x_nearest[region] = torch.where(nearer, x_left.expand_as(disparity), x_nearest[region])
    return nearest, index, x_nearest


_BOUNDS_MARGIN_PX = 2.0
"""`_view_bounds` widens every box by this much: the root of `_seen_from_right` and the
shape test are float computations, so a point at a box's edge must not be culled by rounding."""


def _view_bounds(scene: Scene, view: str) -> torch.Tensor:
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


def _covers(scene: Scene, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
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


def _shade(scene: Scene, surface: torch.Tensor, x_left: torch.Tensor, y: torch.Tensor, view: str) -> torch.Tensor:
    """Colour of the given surfaces at left-view points, as the ``view`` camera ("left" or
    "right") sees them (they differ only in highlights).

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
        disparity = _surface_disparity(plane, curvature, apex, x, y)
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
    gradient_x, gradient_y = _surface_gradient(plane, curvature, apex, x, y)
    relief = scene.relief[scene_index]
    normal = torch.stack([-relief * gradient_x, -relief * gradient_y, -torch.ones_like(x)], dim=-1)
    normal = normal / normal.norm(dim=-1, keepdim=True)
    light = scene.light[scene_index]
    ambient = scene.ambient[scene_index, None]
    diffuse = (normal * light).sum(-1, keepdim=True).clamp_min(0)
    focal, centre_x, centre_y = scene.camera[scene_index].unbind(-1)
    x_view = x - _surface_disparity(plane, curvature, apex, x, y) if view == "right" else x
    to_camera = torch.stack([(centre_x - x_view) / focal, (centre_y - y) / focal, -torch.ones_like(x)], dim=-1)
    half = light + to_camera / to_camera.norm(dim=-1, keepdim=True)
    half = half / half.norm(dim=-1, keepdim=True)
    gloss: torch.Tensor = (normal * half).sum(-1).clamp_min(0) ** at_pixels(scene.shininess)
    highlight = (at_pixels(scene.specular) * gloss)[:, None]
    lit: torch.Tensor = color * (ambient + (1 - ambient) * diffuse) + highlight
    return lit


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


def _texture_bank(batch_size: int, cfg: SceneConfig, draw: _Draw, photos: list[torch.Tensor]) -> torch.Tensor:
    """(B, K, T, T, 3) textures (procedural ones periodic), each standardised to zero mean and
    unit std.

    Slots [0, noise) are 1/f^alpha noise, then dead leaves, then patterns, then photo crops;
    leaves and patterns carry some of their slot's noise on top, so that no texture is perfectly
    clean. Photo crops wrap with a seam, which both views show alike. With repetitive_probability,
    REPETITIVE_TEXTURES clean patterns follow (after texture_count slots), repeating every
    `repetitive_period_texels` texels along u.
    """
    size, count = cfg.texture_size, cfg.texture_count
    procedural = count - cfg.photo_textures
    noise = _standardise(_power_law_noise((batch_size, procedural), size, draw))
    structured = torch.cat(
        [
            _dead_leaves((batch_size, cfg.leaves_textures), size, draw),
            _patterns((batch_size, cfg.pattern_textures), size, draw),
        ],
        dim=1,
    )
    mix = draw.uniform((batch_size, procedural - cfg.noise_textures, 1, 1, 1), 0.0, 0.3)
    textured = _standardise(structured) + mix * noise[:, cfg.noise_textures :]
    parts = [noise[:, : cfg.noise_textures], textured]
    if cfg.photo_textures:
        parts.append(_standardise(_photo_crops((batch_size, cfg.photo_textures), size, draw, photos)))
    if cfg.repetitive_probability > 0:
        period = repetitive_period_texels(size)
        repetitive = _patterns((batch_size, REPETITIVE_TEXTURES), size, draw, period=(period, period), turn=0.0)
        parts.append(_standardise(repetitive))
    return _standardise(torch.cat(parts, dim=1))


def _photo_crops(shape: tuple[int, int], size: int, draw: _Draw, photos: list[torch.Tensor]) -> torch.Tensor:
    """(B, K, T, T, 3) random T x T crops of random photos, each turned by a random multiple of
    90 degrees, mirrored at random and with its colour channels in a random order."""
    count = shape[0] * shape[1]
    which = draw.integers((count,), 0, len(photos) - 1).tolist()
    corner = draw.uniform((count, 2), 0.0, 1.0).tolist()
    turns = draw.integers((count,), 0, 3).tolist()
    mirror = draw.chance((count,), 0.5).tolist()
    channels = torch.argsort(draw.uniform((count, 3), 0.0, 1.0), dim=1)
    crops = []
    for n in range(count):
        photo = photos[which[n]]
        top = int(corner[n][0] * (photo.shape[0] - size))
        left = int(corner[n][1] * (photo.shape[1] - size))
        crop = torch.rot90(photo[top : top + size, left : left + size], turns[n], dims=(0, 1))
        crop = crop.flip(1) if mirror[n] else crop
        crops.append(crop[..., channels[n]])
    return torch.stack(crops).view(*shape, size, size, 3)


def _standardise(textures: torch.Tensor) -> torch.Tensor:
    """Zero mean per channel, unit std over all channels, per texture of (B, K, T, T, 3)."""
    centred = textures - textures.mean(dim=(2, 3), keepdim=True)
    return centred / centred.std(dim=(2, 3, 4), keepdim=True).clamp_min(1e-6)


def _power_law_noise(shape: tuple[int, int], size: int, draw: _Draw) -> torch.Tensor:
    """(B, K, T, T, 3) periodic noise with amplitude spectrum 1/f^alpha, alpha in [0.4, 1.8]: low
    alpha gives fine detail, ~1 natural-photo statistics, high alpha smooth gradients. Colour is a
    shared luminance field plus weaker independent chroma fields."""
    device = draw.device
    fy = torch.fft.fftfreq(size, device=device).view(-1, 1)
    fx = torch.fft.rfftfreq(size, device=device).view(1, -1)
    frequency = torch.sqrt(fx.square() + fy.square())
    frequency[0, 0] = math.inf  # no DC
    alpha = draw.uniform((*shape, 1, 1, 1), 0.4, 1.8)
    amplitude = frequency.pow(-alpha)
    spectrum_shape = (*shape, 4, size, size // 2 + 1)
    spectrum = torch.complex(draw.normal(spectrum_shape), draw.normal(spectrum_shape)) * amplitude
    fields = torch.fft.irfft2(spectrum, s=(size, size))  # (B, K, 4, T, T)
    fields = fields / fields.std(dim=(3, 4), keepdim=True).clamp_min(1e-12)
    saturation = draw.uniform((*shape, 1, 1, 1), 0.0, 0.7)
    rgb: torch.Tensor = fields[:, :, :1] + saturation * fields[:, :, 1:]
    return rgb.permute(0, 1, 3, 4, 2)


def _texel_grid(size: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    coordinates = torch.arange(size, device=device, dtype=torch.float32)
    return coordinates.view(1, 1, 1, -1), coordinates.view(1, 1, -1, 1)  # u (columns), v (rows)


def _dead_leaves(shape: tuple[int, int], size: int, draw: _Draw, discs: int = 64) -> torch.Tensor:
    """(B, K, T, T, 3) dead leaves: discs of random colours painted over each other (wrapping),
    radii log-uniform on [2, T/3] texels, enough of them to cover nearly all of the texture."""
    u, v = _texel_grid(size, draw.device)
    centre_u = draw.uniform((discs, *shape, 1, 1), 0, size).unbind(0)
    centre_v = draw.uniform((discs, *shape, 1, 1), 0, size).unbind(0)
    radius = draw.log_uniform((discs, *shape, 1, 1), 2.0, max(size / 3, 2.0))
    top = torch.zeros((*shape, size, size), dtype=torch.long, device=draw.device)  # 0: no disc yet
    for disc in range(discs):
        du = torch.remainder(u - centre_u[disc] + size / 2, size) - size / 2
        dv = torch.remainder(v - centre_v[disc] + size / 2, size) - size / 2
        top = torch.where(du.square() + dv.square() < radius[disc].square(), disc + 1, top)
    colors = draw.normal((*shape, discs + 1, 3))  # entry 0 is the ground under all discs
    return torch.gather(colors, 2, top.flatten(2)[..., None].expand(-1, -1, -1, 3)).view(*shape, size, size, 3)


def _patterns(
    shape: tuple[int, int],
    size: int,
    draw: _Draw,
    period: tuple[float, float] = (3.0, 40.0),
    turn: float = math.pi,
) -> torch.Tensor:
    """(B, K, T, T, 3) two-colour periodic patterns: stripes, checkers, grid lines or dots, with
    periods log-uniform in `period` texels, turned from repeating along u by up to `turn` radians
    (integer wave vectors keep them periodic in T)."""
    u, v = _texel_grid(size, draw.device)
    period_texels = draw.log_uniform(shape, *period)
    orientation = draw.uniform(shape, 0, turn)
    kx = torch.round(size / period_texels * torch.cos(orientation))
    ky = torch.round(size / period_texels * torch.sin(orientation))
    kx = torch.where((kx == 0) & (ky == 0), 1.0, kx)
    kx, ky = kx[..., None, None], ky[..., None, None]
    phase_a, phase_b = (draw.uniform((*shape, 1, 1), 0, 2 * math.pi) for _ in range(2))
    cos_a = torch.cos(2 * math.pi * (kx * u + ky * v) / size + phase_a)
    cos_b = torch.cos(2 * math.pi * (-ky * u + kx * v) / size + phase_b)
    # (value, threshold) per kind: stripes with a random duty cycle, checkers, thin grid lines, dots.
    values = torch.stack([cos_a, cos_a * cos_b, torch.maximum(cos_a, cos_b), (cos_a + cos_b) / 2], 2)
    thresholds = torch.stack(
        [
            draw.uniform(shape, -0.5, 0.5),
            torch.zeros(shape, device=draw.device),
            draw.uniform(shape, 0.5, 0.9),
            draw.uniform(shape, 0.2, 0.8),
        ],
        dim=2,
    )
    kind = draw.integers((*shape, 1), 0, 3)
    value = torch.gather(values, 2, kind[..., None, None].expand(*shape, 1, size, size))[:, :, 0]
    threshold = torch.gather(thresholds, 2, kind)[..., None]
    sharpness = draw.log_uniform((*shape, 1, 1), 2.0, 30.0)
    mask = torch.sigmoid(sharpness * (value - threshold))[..., None]
    first, second = draw.normal((*shape, 1, 1, 3)), draw.normal((*shape, 1, 1, 3))
    return first + (second - first) * mask


def _photometric(image: torch.Tensor, cfg: PhotometricConfig, draw: _Draw) -> torch.Tensor:
    """Randomly change one view: (B, 3, H, W) in [0, 255] -> the same, changed per sample."""
    batch = image.shape[0]
    per_sample = (batch, 1, 1, 1)
    sigma = torch.where(draw.chance(per_sample, cfg.blur_probability), draw.uniform(per_sample, *cfg.blur_sigma), 0.0)
    image = _gaussian_blur(image, sigma)
    gamma = draw.uniform(per_sample, *cfg.gamma)
    gain = draw.uniform(per_sample, *cfg.gain) * draw.uniform((batch, 3, 1, 1), *cfg.channel_gain)
    offset = draw.uniform(per_sample, *cfg.offset)
    if cfg.vignetting > 0:  # a lens: light falls off with the square of the distance from its centre
        gain = gain * _vignette(image.shape, draw.uniform(per_sample, 0, cfg.vignetting), draw)
    noise = draw.uniform(per_sample, *cfg.noise_sigma) * draw.normal(tuple(image.shape))
    image = 255 * (image / 255).clamp(0, 1).pow(gamma)
    image = (gain * image + offset + noise).clamp(0, 255)
    if cfg.jpeg_probability > 0:
        compressed = draw.chance((batch,), cfg.jpeg_probability)
        quality = draw.integers((batch,), *cfg.jpeg_quality)
        image = _jpeg(image, compressed, quality)
    return image


def _vignette(shape: torch.Size, strength: torch.Tensor, draw: _Draw) -> torch.Tensor:
    """(B, 1, H, W) gains: 1 - strength * (r / r_corner)^2, r the distance from a centre drawn
    within 10 % of the frame's centre, strength (B, 1, 1, 1) the share lost at a corner."""
    batch, _, height, width = shape
    centre = draw.uniform((batch, 2, 1, 1), -0.1, 0.1) * torch.tensor([width, height], device=draw.device).view(
        1, 2, 1, 1
    )
    x = torch.arange(width, device=draw.device).view(1, 1, -1) - (width - 1) / 2 - centre[:, 0]
    y = torch.arange(height, device=draw.device).view(1, -1, 1) - (height - 1) / 2 - centre[:, 1]
    corner = (width**2 + height**2) / 4
    return (1 - strength[:, 0] * (x.square() + y.square()) / corner).clamp_min(0)[:, None]


def _jpeg(image: torch.Tensor, compressed: torch.Tensor, quality: torch.Tensor) -> torch.Tensor:
    """The views `compressed` (B,) saved as JPEG at `quality` (B,) and decoded again (on the host)."""
    if not compressed.any():
        return image
    result = image.clone()
    for index in torch.nonzero(compressed).flatten().tolist():
        rgb = image[index].permute(1, 2, 0).round().to(torch.uint8).cpu().numpy()
        ok, data = cv2.imencode(".jpg", rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(quality[index])])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        decoded = cv2.imdecode(data, cv2.IMREAD_COLOR)
        assert decoded is not None  # OpenCV just wrote it
        result[index] = torch.from_numpy(decoded[:, :, ::-1].copy()).to(image).permute(2, 0, 1)
    return result


def _gaussian_blur(image: torch.Tensor, sigma: torch.Tensor, radius: int = 3) -> torch.Tensor:
    """Separable Gaussian blur with per-sample sigma (B, 1, 1, 1) px; sigma 0 leaves the sample as is.
    Written as shifted sums (no convolution call) so that it is deterministic on every device."""
    offsets = torch.arange(-radius, radius + 1, device=image.device, dtype=image.dtype)
    weights = torch.exp(-offsets.square() / (2 * sigma[..., None].clamp_min(1e-3).square()))
    taps = (weights / weights.sum(-1, keepdim=True)).unbind(-1)  # taps x (B, 1, 1, 1)
    height, width = image.shape[-2:]
    padded = F.pad(image, (radius, radius, 0, 0), mode="replicate")
    image = reduce(torch.add, (w * padded[..., :, k : k + width] for k, w in enumerate(taps)))
    padded = F.pad(image, (0, 0, radius, radius), mode="replicate")
    return reduce(torch.add, (w * padded[..., k : k + height, :] for k, w in enumerate(taps)))
