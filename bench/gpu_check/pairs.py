"""The pairs the stages compute: the real dev pairs where they are found, else procedural scenes."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from .plans import REPO


def dev_pairs(given: Path | None) -> Path | None:
    """The folder of real dev pairs to use, or None (procedural scenes stand in)."""
    candidates = [
        given,
        os.environ.get("STEREO_DEV"),
        REPO / "shared/data/stereo-dev",
        REPO.parent / "shared/data/stereo-dev",
    ]
    return next((Path(c) for c in candidates if c and Path(c).is_dir()), None)


def samples_for(data_dir: Path | None, count: int, height: int, width: int, device: Any) -> tuple[list[Any], str]:
    """`count` pairs with ground truth (StereoSample, host arrays): the dev pairs, or procedural
    scenes of height x width rendered on `device`. Returns them and what they are."""
    from crestereo_pp.stereo_data.readers import open_dataset
    from crestereo_pp.stereo_data.synthetic import SceneConfig, SceneGenerator

    if data_dir is not None:
        dataset = open_dataset(data_dir)
        return [dataset[i] for i in range(min(count, len(dataset)))], f"dev pairs ({data_dir.name})"
    generator = SceneGenerator(SceneConfig(height=height, width=width, max_disparity=width / 6.0), device=device)
    scenes = generator.generate(batch_size=count, seed=11)
    return [scenes.sample(i, f"scene{i}") for i in range(count)], f"procedural scenes {height}x{width}"
