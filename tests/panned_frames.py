"""A stereo video's frames for the specs of warm starts: consecutive RGB pairs (uint8 HxWx3) of one
static procedural scene seen by a camera panning `step_px` px a frame."""

import numpy as np

from crestereo_pp.stereo_data.synthetic import SceneConfig, SceneGenerator


def panned_frames(
    count: int, height: int = 64, width: int = 128, seed: int = 11, step_px: float = 4.0
) -> list[tuple[np.ndarray, np.ndarray]]:
    """`count` consecutive (left, right) pairs of the scene of `seed`."""
    generator = SceneGenerator(SceneConfig(height=height, width=width, surfaces=6, min_surfaces=3, photometric=None))
    return [batch.pair() for batch in generator.pan(seed=seed, frames=count, step=(step_px, 0.0))]
