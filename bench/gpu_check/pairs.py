"""The pairs the stages compute: the real dev pairs where they are found, else procedural scenes."""

from __future__ import annotations

import os
import tarfile
from pathlib import Path
from typing import Any

from .plans import REPO

DEV_ARCHIVE = REPO / "shared" / "stereo-dev.tar.gz"
"""The dev pairs packed for the GPU machine (``pack_dev_pairs``; `--pack-data`). A `shared/` folder
in the checkout travels with it, the `../shared` beside it does not; packed, the pairs take 24 of
their 37 MiB (gzip takes their float32 disparity maps to 40 %), which leaves room in what travels
(plans.MAX_TRAVEL_BYTES) for the weights a GPU run commits."""


def dev_pairs(given: Path | None, scratch: Path | None = None) -> Path | None:
    """The folder of real dev pairs to use, or None (procedural scenes stand in): `given` (with a
    `scratch` folder to unpack into, `given` may be pairs that ``pack_dev_pairs`` packed), else
    $STEREO_DEV, shared/data/stereo-dev in the checkout or beside it, else (with `scratch`)
    DEV_ARCHIVE unpacked."""
    if given is not None and given.is_file() and scratch is not None:
        return unpack_dev_pairs(given, scratch)
    candidates = [
        given,
        os.environ.get("STEREO_DEV"),
        REPO / "shared/data/stereo-dev",
        REPO.parent / "shared/data/stereo-dev",
    ]
    folder = next((Path(c) for c in candidates if c and Path(c).is_dir()), None)
    if folder is not None or scratch is None or not DEV_ARCHIVE.is_file():
        return folder
    return unpack_dev_pairs(DEV_ARCHIVE, scratch)


def pack_dev_pairs(folder: Path, archive: Path = DEV_ARCHIVE) -> int:
    """Pack the dev pairs of `folder` as `archive` (.tar.gz holding the folder as stereo-dev/);
    returns its size in bytes."""
    archive.parent.mkdir(parents=True, exist_ok=True)
    with tarfile.open(archive, "w:gz") as tar:
        tar.add(folder, arcname="stereo-dev")
    return archive.stat().st_size


def unpack_dev_pairs(archive: Path, scratch: Path) -> Path:
    """The folder of dev pairs that `pack_dev_pairs` packed as `archive`, unpacked into `scratch`."""
    with tarfile.open(archive, "r:gz") as tar:
        tar.extractall(scratch, filter="data")
    return scratch / "stereo-dev"


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
