"""A raw stereo pair of a known scene from a calibrated, distorted camera (for the rig tests):
a textured plane PLANE_Z metres in front of the left camera, seen by two cameras with lens
distortion, the right one turned a little and 12 cm to the right (OpenCV's K1, D1, K2, D2, R, T)."""

from pathlib import Path

import cv2
import numpy as np

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
