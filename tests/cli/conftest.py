"""Fixtures: small stereo pairs on disk, in the stereo-dev folder layout."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from crestereo_pp.stereo_data.formats import write_pfm
from shared_data import SMALL_STEREO_DEV_PAIR, STEREO_DEV


def write_shifted_pair(folder: Path, disparity: int, height: int = 64, width: int = 96, seed: int = 0) -> None:
    """folder/{left.png, right.png, disp.pfm}: a random texture seen with a constant `disparity`
    (left x matches right x - disparity); the leftmost `disparity` columns have no match and
    their ground truth is unknown (+inf)."""
    rng = np.random.default_rng(seed)
    texture = cv2.resize(
        rng.integers(0, 256, (height, width // 2 + disparity, 3), dtype=np.uint8), (width + disparity, height)
    )
    right = texture[:, disparity:]
    left = texture[:, :width]  # left(x) = texture(x) = right(x - disparity)
    ground_truth = np.full((height, width), float(disparity), np.float32)
    ground_truth[:, :disparity] = np.inf
    folder.mkdir(parents=True)
    cv2.imwrite(str(folder / "left.png"), left[:, :, ::-1])
    cv2.imwrite(str(folder / "right.png"), right[:, :, ::-1])
    write_pfm(folder / "disp.pfm", ground_truth)


@pytest.fixture
def pairs_dir(tmp_path: Path) -> Path:
    """Two 64x96 pairs, `shift4` and `shift9`, in the NAME/{left,right.png, disp.pfm} layout."""
    root = tmp_path / "pairs"
    write_shifted_pair(root / "shift4", 4, seed=1)
    write_shifted_pair(root / "shift9", 9, seed=2)
    return root


@pytest.fixture
def small_stereo_dev(tmp_path: Path) -> Path:
    """A folder holding only the smallest real stereo-dev pair (linked), or a skip."""
    if not (STEREO_DEV / SMALL_STEREO_DEV_PAIR).is_dir():
        pytest.skip(f"real pairs not available: {STEREO_DEV} does not exist (see tests/shared_data.py)")
    root = tmp_path / "stereo-dev-small"
    root.mkdir()
    (root / SMALL_STEREO_DEV_PAIR).symlink_to(STEREO_DEV / SMALL_STEREO_DEV_PAIR)
    return root
