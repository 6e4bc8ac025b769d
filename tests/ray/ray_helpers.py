"""Helpers of the Ray tests: small real stereo pairs, and the processes a local Ray cluster runs."""

from __future__ import annotations

import subprocess
from pathlib import Path

import cv2
import numpy as np

from shared_data import SMALL_STEREO_DEV_PAIR, STEREO_DEV

CROP_HEIGHT, CROP_WIDTH = 96, 160


def real_crops(count: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """`count` different 96x160 crops (BGR) of the small real pair, left and right alike."""
    folder = STEREO_DEV / SMALL_STEREO_DEV_PAIR
    left, right = (cv2.imread(str(folder / name)) for name in ("left.png", "right.png"))
    assert left is not None and right is not None, f"cannot read {folder}"
    rows = np.linspace(0, left.shape[0] - CROP_HEIGHT, count).astype(int)
    columns = np.linspace(0, left.shape[1] - CROP_WIDTH, count).astype(int)[::-1]
    return [
        (left[y : y + CROP_HEIGHT, x : x + CROP_WIDTH], right[y : y + CROP_HEIGHT, x : x + CROP_WIDTH])
        for y, x in zip(rows, columns, strict=True)
    ]


def write_pairs(folder: Path, count: int) -> tuple[Path, Path]:
    """Folders `left/` and `right/` under `folder` holding `count` real pairs (pair_00.png ...)."""
    lefts, rights = folder / "left", folder / "right"
    lefts.mkdir(parents=True)
    rights.mkdir()
    for index, (left, right) in enumerate(real_crops(count)):
        cv2.imwrite(str(lefts / f"pair_{index:02d}.png"), left)
        cv2.imwrite(str(rights / f"pair_{index:02d}.png"), right)
    return lefts, rights


def ray_processes() -> list[int]:
    """Process ids of Ray's cluster processes (its GCS server, raylets and workers) on this machine."""
    listing = subprocess.run(["ps", "-eo", "pid=,args="], capture_output=True, text=True, check=True).stdout
    markers = ("gcs_server", "raylet", "ray::")
    return [int(line.split()[0]) for line in listing.splitlines() if any(marker in line for marker in markers)]


def replica_processes() -> list[int]:
    """Process ids of the service's Ray Serve replicas."""
    listing = subprocess.run(["ps", "-eo", "pid=,args="], capture_output=True, text=True, check=True).stdout
    return [int(line.split()[0]) for line in listing.splitlines() if "ServeReplica:crestereo-pp" in line]
