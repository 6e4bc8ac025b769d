"""`SceneGenerator`: draws scenes and renders both views exactly, with their ground truth."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..photos import load_photos
from ..readers import StereoSample
from .config import SceneConfig
from .draw import Draw
from .photometric import apply_photometric
from .rectification import draw_row_offsets, offset_rows
from .sampling import draw_scenes
from .scene import Scene, SyntheticBatch
from .shading import shade
from .visibility import nearest_surface

_OCCLUSION_TOLERANCE = 1e-3  # px: a surface must be this much nearer to hide a match


class SceneGenerator:
    """Draws and renders batches of procedural stereo scenes on ``device``."""

    def __init__(self, config: SceneConfig, device: str | torch.device = "cpu") -> None:
        self.config = config
        self.device = torch.device(device)
        self._x = torch.arange(config.width, device=self.device, dtype=torch.float32).view(1, 1, 1, -1)
        self._y = torch.arange(config.height, device=self.device, dtype=torch.float32).view(1, 1, -1, 1)
        self._photos = load_photos(config.texture_size, self.device) if config.photo_textures else []

    def generate(self, batch_size: int, seed: int) -> SyntheticBatch:
        """Draw, render and (if configured) move the right views off their rows and photometrically
        augment ``batch_size`` pairs."""
        draw = Draw.seeded(seed, self.device)
        batch = self.render(draw_scenes(batch_size, self.config, draw, self._photos))
        if self.config.row_offset_probability > 0:  # drawn only then: other settings keep their scenes
            batch.row_offset = draw_row_offsets(batch_size, self.config, draw)
            batch.right = offset_rows(batch.right, batch.row_offset)
        if self.config.photometric is not None:
            batch.left = apply_photometric(batch.left, self.config.photometric, draw)
            batch.right = apply_photometric(batch.right, self.config.photometric, draw)
        return batch

    def samples(self, count: int, seed: int, batch_size: int = 4) -> list[StereoSample]:
        """`count` pairs as a dataset of real pairs reads them (`SyntheticBatch.sample`), drawn
        `batch_size` at a time: the batch from seed + i holds pairs i.. (named
        ``procedural_{seed + i}_{k}``), as `training.calibrate` draws its scenes."""
        samples = []
        for first in range(0, count, batch_size):
            size = min(batch_size, count - first)
            batch = self.generate(size, seed=seed + first)
            samples += [batch.sample(k, f"procedural_{seed + first}_{k}") for k in range(size)]
        return samples

    def pan(self, seed: int, frames: int, step: tuple[float, float]) -> list[SyntheticBatch]:
        """A video with exact ground truth: `frames` renders (batches of one, without photometric
        changes) of one static scene seen by a camera panning `step` (dx, dy) px per frame."""
        scene = self.sample_scene(batch_size=1, seed=seed)
        return [self.render(scene.translated(step[0] * t, step[1] * t)) for t in range(frames)]

    def sample_scene(self, batch_size: int, seed: int) -> Scene:
        """The scenes that ``generate(batch_size, seed)`` renders."""
        draw = Draw.seeded(seed, self.device)
        return draw_scenes(batch_size, self.config, draw, self._photos)

    def render(self, scene: Scene) -> SyntheticBatch:
        """Render both views of ``scene`` exactly, without photometric changes."""
        x, y = self._x, self._y
        left_disparity, left_surface, _ = nearest_surface(scene, x, y, "left")
        if self.config.supersample == 1:  # the point samples are the pixel centres: shade what was found
            left = shade(scene, left_surface, x.expand_as(left_disparity), y, "left")
        else:
            left = self._view(scene, "left")
        right = self._view(scene, "right")
        x_match = x - left_disparity
        match_disparity, _, _ = nearest_surface(scene, x_match, y, "right")
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
        _, surface, x_left = nearest_surface(scene, x, y, view)
        color = shade(scene, surface, x_left.expand_as(surface), y, view)
        return F.avg_pool2d(color, k) if k > 1 else color
