"""Drawn scenes (`Scene`, the surfaces' parameters) and rendered pairs (`SyntheticBatch`)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from ..readers import StereoSample

MAX_SIDES = 24
"""Polygons have 3..MAX_SIDES vertices; a MAX_SIDES-gon with equal radii stands for an ellipse."""


@dataclass
class Scene:
    """B scenes of S surfaces each, in output pixel coordinates of the left view.

    A surface is the set of points (x, y) whose shape-frame coordinates (u, v) = to_shape @ (x, y, 1)
    lie in its star polygon and not in its hole. The polygon has ``sides`` vertices, vertex j at
    angle ``phase + 2*pi*j/sides`` and distance ``radii[j]`` from (0, 0). A surface with a zero
    ``to_shape`` covers the whole plane (the background, surface 0 in generated scenes).

    plane: (B, S, 3) float, (a, b, c): the surface's disparity is a*x + b*y + c px (a < 1), plus
        the quadratic term of ``curvature`` (see `geometry.surface_disparity`).
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
    reflection: (B, S) float, grey-level std of the farther scene the surface reflects (0: none);
        reflection_depth: (B, S), that scene's disparity as a share of the surface's, in [0, 1);
        reflection_texture: (B, S) int64, which of the K textures it shows; to_reflection: (B, S,
        2, 3) float, affine map from where it is seen, (x, y) px of the left view, to texel
        coordinates (wrapping). The right view sees at x what the left view sees at
        x + reflection_depth * d, d the surface's disparity there: the reflection moves between
        the views by its own disparity, not by the surface's.
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
    reflection: torch.Tensor
    reflection_depth: torch.Tensor
    reflection_texture: torch.Tensor
    to_reflection: torch.Tensor
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
            to_reflection=shifted(self.to_reflection),
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
        [0, wide_max_disparity]); left pixel (x, y) matches right pixel (x - d, y) (a row lower by
        `row_offset`'s dy where that is set). Dense and exact,
        occluded pixels included.
    valid: (B, 1, H, W) bool, where the ground truth is defined: everywhere (kept for the contract
        shared with real datasets).
    occluded: (B, 1, H, W) bool, left pixels whose match is hidden by a nearer surface in the right
        view, or out of its frame (x - d < 0).
    row_offset: (B, 3) float32 px, (centre, across, down): the right view's rows against the left's
        (`rectification.draw_row_offsets`); None where they agree exactly, as rendered.
    """

    left: torch.Tensor
    right: torch.Tensor
    disparity: torch.Tensor
    valid: torch.Tensor
    occluded: torch.Tensor
    row_offset: torch.Tensor | None = None

    def pair(self, index: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Pair `index` as images: (left, right) uint8 HxWx3 RGB, on the host."""
        left, right = (
            view[index].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).cpu().numpy()
            for view in (self.left, self.right)
        )
        return left, right

    def sample(self, index: int, name: str) -> StereoSample:
        """Pair `index` as a real pair is read (`StereoSample` named `name`): the uint8 views of
        `pair`, the disparity (+inf where not `valid`), and the non-occluded mask."""
        left, right = self.pair(index)
        valid = self.valid[index, 0].cpu().numpy()
        disparity = np.where(valid, self.disparity[index, 0].cpu().numpy(), np.inf).astype(np.float32)
        return StereoSample(name, left, right, disparity, valid, valid & ~self.occluded[index, 0].cpu().numpy())
