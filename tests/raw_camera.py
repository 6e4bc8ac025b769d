"""A raw stereo pair of a known scene from a calibrated, distorted camera (for the rig tests):
a textured plane PLANE_Z metres in front of the left camera, seen by two cameras with lens
distortion, the right one turned a little and 12 cm to the right (OpenCV's K1, D1, K2, D2, R, T);
and a real rectified pair made raw by a known rotation or lens distortion (`unrectify`)."""

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from crestereo_pp.stereo_data.readers import StereoSample, open_dataset
from shared_data import SMALL_STEREO_DEV_PAIR, STEREO_DEV

WIDTH, HEIGHT = 320, 240
K1 = np.array([[400.0, 0, 158], [0, 402.0, 121], [0, 0, 1]])
K2 = np.array([[405.0, 0, 163], [0, 404.0, 118], [0, 0, 1]])
D1 = np.array([-0.12, 0.05, 0.001, -0.001, 0.0])
D2 = np.array([-0.10, 0.04, 0.0, 0.001, 0.0])
R = cv2.Rodrigues(np.array([0.004, -0.02, 0.006]))[0]  # the right camera slightly turned
T = np.array([-0.12, 0.003, 0.002])  # metres: the right camera 12 cm to the right
PLANE_Z = 1.6  # metres in front of the left camera


def opencv_file(path: Path, **entries: object) -> Path:
    """A calibration as cv2.FileStorage writes it (YAML or JSON by the suffix)."""
    values = {"K1": K1, "D1": D1, "K2": K2, "D2": D2, "R": R, "T": T, "image_width": WIDTH, "image_height": HEIGHT}
    values.update(entries)
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for key, value in values.items():
        if value is not None:
            storage.write(key, value)
    storage.release()
    return path


def opencv_yaml_with(path: Path, key: str, text: str) -> str:
    """The calibration as cv2.FileStorage writes it (YAML), with the entry `key` written as `text`
    (raw YAML, what follows `key:`) instead."""
    return opencv_file(path, **{key: None}).read_text() + f"{key}: {text}\n"


HANG = "%YAML:1.0\n---\nK1: !!binary |\n  " + "A" * 32 + "\n"
"""A calibration that held OpenCV's own parser (cv2.FileStorage) for 10-22 s."""

MATRIX = "!!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: {dt}\n   data: [ {data} ]"
IDENTITY = "1., 0., 0., 0., 1., 0., 0., 0., 1."
MALFORMED = {
    # id: (entry, its YAML text, the field the refusal names)
    "1e5x1e5 matrix": ("K1", MATRIX.format(rows=100000, cols=100000, dt="d", data=IDENTITY), "K1"),
    "2^31 rows": ("K1", MATRIX.format(rows=2**31, cols=1, dt="d", data=IDENTITY), "K1"),
    "-3 rows": ("K1", MATRIX.format(rows=-3, cols=-3, dt="d", data=IDENTITY), "K1"),
    "data of another length": ("K1", MATRIX.format(rows=3, cols=3, dt="d", data="1., 0., 0., 1."), "K1"),
    "dt x": ("K1", MATRIX.format(rows=3, cols=3, dt="x", data=IDENTITY), "K1"),
    "3-channel dt": ("K1", MATRIX.format(rows=3, cols=1, dt='"3d"', data=IDENTITY), "K1"),
    "nd-matrix": ("K1", f"!!opencv-nd-matrix\n   sizes: [ 3, 3, 1 ]\n   dt: d\n   data: [ {IDENTITY} ]", "K1"),
    "K1 a map": ("K1", "\n   fx: 400.\n   fy: 400.", "K1"),
    "K1 a string": ("K1", "camera", "K1"),
    "K1 a nested map": ("K1", "\n   rows:\n      cols: 3", "K1"),
    "1e309": ("T", "[ -0.12, 1e309, 0. ]", "T"),
    "binary tag": ("K1", "!!binary |\n  AAAA", "K1"),
    "anchor": ("T", "&t [ -0.12, 0., 0. ]", "T"),
    "alias": ("K2", "*k1", "K2"),
    "block scalar": ("R", "|\n  1 0 0", "R"),
    "width 1e300": ("image_width", "1e300", "image_size"),
    "width 2^31": ("image_width", str(2**31), "image_size"),
    'width "256"': ("image_width", '"256"', "image_size"),
}
"""Calibrations OpenCV would read, or choke on, that are not a calibration: each refused."""


def texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Grey levels of the plane at metric coordinates (x, y): smooth, with detail at many scales."""
    value = sum(np.sin(f * x + 1.3 * k) * np.cos(0.8 * f * y + k) / (k + 1) for k, f in enumerate((9, 23, 41, 67)))
    return (128 + 60 * value).astype(np.float32)


def raw_view(k: np.ndarray, d: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """The plane Z = PLANE_Z (left camera frame) seen by a distorted camera whose frame is
    X_cam = rotation @ X_left + translation."""
    pixels = np.stack(np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT)), -1).reshape(-1, 1, 2).astype(np.float64)
    rays = cv2.undistortPoints(pixels, k, d, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-9))
    rays = np.concatenate([rays.reshape(-1, 2), np.ones((WIDTH * HEIGHT, 1))], axis=1)  # camera frame
    to_left = rotation.T
    origin = -to_left @ translation  # the camera centre in the left frame
    directions = rays @ to_left.T
    s = (PLANE_Z - origin[2]) / directions[:, 2]
    points = origin + s[:, None] * directions
    return texture(points[:, 0], points[:, 1]).reshape(HEIGHT, WIDTH)


def ros_camera_info_files(folder: Path) -> tuple[Path, Path]:
    """The same rig as two ROS camera_info YAML files (left.yaml, right.yaml in `folder`), as
    `camera_calibration` writes them: each camera's K, D and its rectification R, P."""
    r1, r2, p1, p2, *_ = cv2.stereoRectify(
        K1, D1, K2, D2, (WIDTH, HEIGHT), R, T.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0
    )

    def entry(name: str, matrix: np.ndarray) -> str:
        rows, cols = matrix.shape if matrix.ndim == 2 else (1, matrix.size)
        data = ", ".join(repr(float(v)) for v in matrix.ravel())
        return f"{name}:\n  rows: {rows}\n  cols: {cols}\n  data: [{data}]\n"

    paths = []
    for side, k, d, r, p in (("left", K1, D1, r1, p1), ("right", K2, D2, r2, p2)):
        text = f"image_width: {WIDTH}\nimage_height: {HEIGHT}\ncamera_name: {side}\n"
        text += entry("camera_matrix", k) + "distortion_model: plumb_bob\n" + entry("distortion_coefficients", d)
        text += entry("rectification_matrix", r) + entry("projection_matrix", p)
        paths.append(folder / f"{side}.yaml")
        paths[-1].write_text(text)
    return paths[0], paths[1]


# --- a real rectified pair made raw again --------------------------------------------------------

DEV_FOCAL_PX, DEV_BASELINE_M = 400.0, 0.1  # the camera given to a rectified dev pair


@dataclass(frozen=True)
class UnrectifiedPair:
    """A real rectified pair made raw by a known change of its camera, with what undoes it.

    left, right: uint8 HxWx3 RGB as the changed camera sees them; calibration: the OpenCV entries
    (K1, D1, K2, D2, R, T, image size) of that camera; depth: float HxW metres along the left
    camera's axis at the raw left image's pixels, NaN where the ground truth has none.
    """

    left: np.ndarray
    right: np.ndarray
    calibration: dict[str, object]
    depth: np.ndarray


def small_dev_sample() -> StereoSample:
    """The smallest real stereo-dev pair with its ground truth, or a skip where the pairs are not here."""
    return dev_sample(SMALL_STEREO_DEV_PAIR)


def dev_sample(name: str) -> StereoSample:
    """The real stereo-dev pair `name` with its ground truth, or a skip where the pairs are not here."""
    if not (STEREO_DEV / name).is_dir():
        pytest.skip(f"real pairs not available: {STEREO_DEV} does not exist (see tests/shared_data.py)")
    dataset = open_dataset(STEREO_DEV)
    return dataset[[files.name for files in dataset.files].index(name)]


def unrectify(left: np.ndarray, right: np.ndarray, disparity: np.ndarray, change: str) -> UnrectifiedPair:
    """Take a rectified pair (its left disparity, +inf unknown) as seen by a pinhole camera of
    focal DEV_FOCAL_PX and baseline DEV_BASELINE_M, and change the camera: `"rotation"` turns the
    right camera by about 1.5 degrees (the right image warped by the homography K R^T K^-1), and
    `"distortion"` gives both lenses radial distortion (k1 = -0.15, k2 = 0.05)."""
    height, width = disparity.shape
    k = np.array([[DEV_FOCAL_PX, 0, (width - 1) / 2], [0, DEV_FOCAL_PX, (height - 1) / 2], [0, 0, 1]])
    baseline = np.array([-DEV_BASELINE_M, 0.0, 0.0])
    no_distortion = np.zeros(5)
    with np.errstate(divide="ignore"):
        true_depth = np.where(
            np.isfinite(disparity) & (disparity > 0), DEV_FOCAL_PX * DEV_BASELINE_M / disparity, np.nan
        )
    entries: dict[str, object] = {"K1": k, "K2": k, "image_width": width, "image_height": height}
    if change == "rotation":
        rotation = cv2.Rodrigues(np.array([0.01, -0.015, 0.02]))[0]  # X_right = rotation @ X_right_before
        homography = k @ rotation.T @ np.linalg.inv(k)  # a raw right pixel -> where the rectified right saw it
        raw_right = cv2.warpPerspective(
            right, homography, (width, height), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        )
        entries.update(D1=no_distortion, D2=no_distortion, R=rotation, T=rotation @ baseline)
        return UnrectifiedPair(left, raw_right, entries, true_depth.astype(np.float32))
    if change != "distortion":
        raise ValueError(f"unknown change {change!r}")
    distortion = np.array([-0.15, 0.05, 0.0, 0.0, 0.0])
    pixels = np.stack(np.meshgrid(np.arange(width), np.arange(height)), -1).reshape(-1, 1, 2).astype(np.float64)
    seen = cv2.undistortPoints(pixels, k, distortion, P=k).reshape(height, width, 2).astype(np.float32)
    raw = [cv2.remap(image, seen[..., 0], seen[..., 1], cv2.INTER_LINEAR) for image in (left, right)]
    raw_depth = cv2.remap(
        true_depth.astype(np.float32), seen[..., 0], seen[..., 1], cv2.INTER_NEAREST, borderValue=np.nan
    )
    entries.update(D1=distortion, D2=distortion, R=np.eye(3), T=baseline)
    return UnrectifiedPair(raw[0], raw[1], entries, raw_depth)


def share_within(depth: np.ndarray, truth: np.ndarray, tolerance: float = 0.05) -> float:
    """The share of the pixels with a true depth whose depth is within `tolerance` (relative) of it."""
    known = np.isfinite(truth)
    return float((np.abs(depth[known] - truth[known]) <= tolerance * truth[known]).mean())
