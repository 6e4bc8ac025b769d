"""A calibrated stereo camera: read its calibration, rectify its pairs, and bring maps back.

    rig = read_rig("stereo.yaml")          # OpenCV's K1, D1, K2, D2, R, T; or two ROS camera_info files
    rectifier = Rectifier(rig)                        # maps computed once for the rig's image size
    left_r, right_r = rectifier.rectify(left, right)  # rectified pair: matches lie on the same row
    disparity, uncertainty = predictor.predict(left_r, right_r)
    depth_rig = rectifier.depth_calibration           # focal length, baseline, principal point (metres)
    disparity_original = rectifier.to_original(disparity)  # in the original left image's pixels
    depth_original = rectifier.to_original_depth(depth)    # metres along the original camera's axis

Conventions are OpenCV's: K is the 3x3 camera matrix, D the distortion coefficients (4, 5, 8, 12
or 14), and R, T take a point from the left camera's frame into the right camera's (so a right
camera to the right of the left one has T[0] < 0); T's unit is the depth's unit (metres here).
A ROS pair of ``sensor_msgs/CameraInfo`` files carries its rectification already (R and P per
camera): it is used as given. Disparity is in rectified pixels, positive: left x matches right
x - d on the same rectified row.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path

import cv2
import numpy as np

from .pointcloud import Calibration

__all__ = ["RigError", "StereoRig", "Rectifier", "read_rig", "parse_rig"]

DISTORTION_LENGTHS = (4, 5, 8, 12, 14)


class RigError(ValueError):
    """A calibration that cannot be used; ``field`` names what is wrong (e.g. ``"T"``)."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")
        self.field, self.reason = field, message


@dataclass(frozen=True, eq=False)
class StereoRig:
    """A rectifiable stereo camera for images of ``image_size`` = (width, height) px.

    k1, k2: (3, 3) camera matrices; d1, d2: distortion coefficients; r1, r2: (3, 3) rotations into
    the rectified frames; p1, p2: (3, 4) projections of the rectified cameras (p2[0, 3] =
    -focal * baseline).
    """

    image_size: tuple[int, int]
    k1: np.ndarray
    d1: np.ndarray
    k2: np.ndarray
    d2: np.ndarray
    r1: np.ndarray
    r2: np.ndarray
    p1: np.ndarray
    p2: np.ndarray

    @property
    def focal_px(self) -> float:
        return float(self.p1[0, 0])

    @property
    def baseline(self) -> float:
        """Distance between the camera centres, in the unit of T (metres)."""
        return float(-self.p2[0, 3] / self.p2[0, 0])

    def to_json(self) -> str:
        """The rig as JSON numbers (float64 round-trips exactly); `from_json` reads it back."""
        return json.dumps({field.name: np.asarray(getattr(self, field.name)).tolist() for field in fields(self)})

    @staticmethod
    def from_json(text: str) -> StereoRig:
        """The rig of `to_json`'s text, checked again (shapes, finite numbers, a positive focal
        length and baseline): RigError where it is not a rig."""
        try:
            values = json.loads(text)
        except ValueError:
            values = None
        if not isinstance(values, dict):
            raise RigError("calibration", "not a rig's JSON")

        def array(key: str, shapes: Sequence[tuple[int, ...]]) -> np.ndarray:
            try:
                value = np.asarray(values[key], np.float64)
            except (KeyError, TypeError, ValueError):
                raise RigError(key, "missing or not numbers") from None
            return _shaped(key, value.reshape(-1), shapes)

        width, height = array("image_size", [(2,)])
        if not (width >= 1 and height >= 1 and width.is_integer() and height.is_integer()):
            raise RigError("image_size", f"expected positive whole numbers of pixels, got {width}x{height}")
        distortion = [(n,) for n in DISTORTION_LENGTHS]
        rig = StereoRig(
            (int(width), int(height)),
            array("k1", [(3, 3)]),
            array("d1", distortion),
            array("k2", [(3, 3)]),
            array("d2", distortion),
            array("r1", [(3, 3)]),
            array("r2", [(3, 3)]),
            array("p1", [(3, 4)]),
            array("p2", [(3, 4)]),
        )
        if not (rig.focal_px > 0 and rig.baseline > 0):
            raise RigError("calibration", "the rectified cameras need a positive focal length and baseline")
        return rig


def read_rig(paths: str | Path | Sequence[str | Path]) -> StereoRig:
    """The rig of one OpenCV calibration file (YAML or JSON as ``cv2.FileStorage`` writes it) or
    of two ROS ``camera_info`` YAML files (left, then right). RigError where it is unusable."""
    files = [Path(paths)] if isinstance(paths, str | Path) else [Path(p) for p in paths]
    if len(files) not in (1, 2):
        raise RigError("calibration", f"give one OpenCV file or two ROS camera_info files, got {len(files)}")
    try:
        texts = [file.read_text() for file in files]
    except (OSError, UnicodeDecodeError) as error:
        raise RigError("calibration", f"cannot read it: {error}") from None
    return parse_rig(*texts)


def parse_rig(text: str, right_text: str | None = None) -> StereoRig:
    """``read_rig`` on file contents: one OpenCV calibration, or the left and right camera_info."""
    if right_text is None:
        return _opencv_rig(_storage(text, "calibration"))
    return _ros_rig(_storage(text, "left camera_info"), _storage(right_text, "right camera_info"))


class Rectifier:
    """Rectification of one rig's pairs; its maps are computed once, here."""

    def __init__(self, rig: StereoRig) -> None:
        self.rig = rig
        size = rig.image_size
        self._maps = [
            cv2.initUndistortRectifyMap(k, d, r, p, size, cv2.CV_32FC1)
            for k, d, r, p in ((rig.k1, rig.d1, rig.r1, rig.p1), (rig.k2, rig.d2, rig.r2, rig.p2))
        ]
        # Where each original left pixel lands in the rectified left image (for `to_original`).
        width, height = size
        grid = np.stack(np.meshgrid(np.arange(width), np.arange(height)), -1).reshape(-1, 1, 2).astype(np.float64)
        landed = cv2.undistortPoints(
            grid,
            rig.k1,
            rig.d1,
            R=rig.r1,
            P=rig.p1,
            criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-6),
        )
        self._back = landed.reshape(height, width, 2).astype(np.float32)

    @property
    def depth_calibration(self) -> Calibration:
        """Focal length, baseline and principal point of the rectified left camera."""
        p1 = self.rig.p1
        return Calibration(self.rig.focal_px, self.rig.baseline, float(p1[0, 2]), float(p1[1, 2]))

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The pair (HxW or HxWxC images of the rig's size) rectified, bilinearly; pixels with no
        source are black. RigError where the pair's size is not the calibration's."""
        width, height = self.rig.image_size
        for name, image in (("left", left), ("right", right)):
            if image.shape[:2] != (height, width):
                raise RigError(
                    "image_size",
                    f"the calibration is for {width}x{height} images, the {name} image is "
                    f"{image.shape[1]}x{image.shape[0]}",
                )
        rectified = [
            cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            for image, (map_x, map_y) in zip((left, right), self._maps, strict=True)
        ]
        return rectified[0], rectified[1]

    def to_original(self, rectified: np.ndarray, missing: float = float("nan")) -> np.ndarray:
        """A map of the rectified left frame (float HxW) resampled into the original left image's
        pixel grid, bilinearly, as float32; ``missing`` where an original pixel has no rectified
        counterpart (or its neighbours there are not finite: +inf disparity stays unknown)."""
        back_x, back_y = self._back[..., 0], self._back[..., 1]
        resampled = cv2.remap(
            rectified.astype(np.float32),
            back_x,
            back_y,
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=float("nan"),
        )
        return np.where(np.isfinite(resampled), resampled, np.float32(missing)).astype(np.float32)

    def to_original_depth(self, depth: np.ndarray) -> np.ndarray:
        """Metric depth of the rectified left frame (float HxW: Z along the rectified camera's
        axis, +inf where none) as depth along the ORIGINAL left camera's axis, in the original
        left image's pixels (float32; +inf where none). The rectified camera is the original one
        turned by R1 (X_rect = R1 @ X_orig), so Z_orig = Z_rect * (R1[:, 2] . ((x - cx)/f, (y - cy)/f, 1))."""
        p1, r1 = self.rig.p1, self.rig.r1
        height, width = depth.shape
        x = (np.arange(width) - p1[0, 2]) / p1[0, 0]
        y = (np.arange(height) - p1[1, 2]) / p1[1, 1]
        along = r1[0, 2] * x[None, :] + r1[1, 2] * y[:, None] + r1[2, 2]
        return self.to_original((depth * along).astype(np.float32), np.inf)


def _storage(text: str, what: str) -> cv2.FileStorage:
    try:
        storage = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (cv2.error, SystemError):  # OpenCV's parser fails either way on text it cannot read
        storage = None
    if storage is None or not storage.isOpened():
        raise RigError(what, "not a YAML or JSON file that OpenCV can read")
    return storage


def _matrix(storage: cv2.FileStorage, key: str, shapes: Sequence[tuple[int, ...]]) -> np.ndarray:
    """An OpenCV matrix entry, as float64 of one of `shapes` (flat lengths match any layout)."""
    node = storage.getNode(key)
    if node.empty():
        raise RigError(key, "missing")
    value = _numbers(node) if node.isSeq() else node.mat()
    if value is None:
        raise RigError(key, "expected a matrix or a list of numbers")
    return _shaped(key, np.asarray(value, np.float64), shapes)


def _numbers(sequence: cv2.FileNode) -> np.ndarray:
    """A YAML/JSON list of numbers as float64."""
    return np.array([sequence.at(i).real() for i in range(sequence.size())], np.float64)


def _shaped(key: str, value: np.ndarray, shapes: Sequence[tuple[int, ...]]) -> np.ndarray:
    for shape in shapes:
        if value.size == int(np.prod(shape)):
            value = value.reshape(shape)
            if not np.isfinite(value).all():
                raise RigError(key, "holds a value that is not a finite number")
            return value
    wanted = " or ".join("x".join(map(str, shape)) for shape in shapes)
    raise RigError(key, f"expected {wanted} values, got {value.size}")


def _image_size(storage: cv2.FileStorage) -> tuple[int, int]:
    if not storage.getNode("image_size").empty():
        width, height = _matrix(storage, "image_size", [(2,)])
    else:
        nodes = [storage.getNode(key) for key in ("image_width", "image_height")]
        if any(node.empty() for node in nodes):
            raise RigError("image_size", "missing: give image_size [width, height], or image_width and image_height")
        width, height = (node.real() for node in nodes)
    if not (width >= 1 and height >= 1 and float(width).is_integer() and float(height).is_integer()):
        raise RigError("image_size", f"expected positive whole numbers of pixels, got {width}x{height}")
    return int(width), int(height)


def _camera(k: np.ndarray, k_name: str) -> None:
    if not (k[0, 0] > 0 and k[1, 1] > 0 and np.allclose(k[2], (0.0, 0.0, 1.0))):
        raise RigError(k_name, "not a camera matrix: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")


def _opencv_rig(storage: cv2.FileStorage) -> StereoRig:
    size = _image_size(storage)
    k1, k2 = (_matrix(storage, key, [(3, 3)]) for key in ("K1", "K2"))
    d1, d2 = (_matrix(storage, key, [(n,) for n in DISTORTION_LENGTHS]) for key in ("D1", "D2"))
    _camera(k1, "K1")
    _camera(k2, "K2")
    rotation = _matrix(storage, "R", [(3, 3), (3,)])
    if rotation.shape == (3,):
        rotation = cv2.Rodrigues(rotation)[0]  # a rotation vector
    if not (np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-3) and np.linalg.det(rotation) > 0):
        raise RigError("R", "not a rotation matrix (orthonormal, determinant 1)")
    translation = _matrix(storage, "T", [(3,)])
    baseline = float(np.linalg.norm(translation))
    if baseline == 0:
        raise RigError("T", "the baseline is zero: the two cameras are at one place")
    if abs(translation[0]) < 2 * max(abs(translation[1]), abs(translation[2])):
        raise RigError(
            "T", f"the cameras are not side by side ({translation.tolist()}): this matcher needs a horizontal baseline"
        )
    if translation[0] > 0:
        raise RigError(
            "T", "the right camera is to the left of the left one (T[0] > 0): swap the images and the cameras"
        )
    r1, r2, p1, p2, *_ = cv2.stereoRectify(
        k1, d1, k2, d2, size, rotation, translation.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0
    )
    if not (np.isfinite(p1).all() and np.isfinite(p2).all() and p1[0, 0] > 0):
        raise RigError("calibration", "OpenCV cannot rectify these cameras")
    return StereoRig(size, k1, d1, k2, d2, r1, r2, p1, p2)


RosCamera = tuple[tuple[int, int], np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""image size, K, D, rectification R, projection P of one ROS camera_info."""


def _ros_camera(storage: cv2.FileStorage, side: str) -> RosCamera:
    def entry(key: str, shapes: Sequence[tuple[int, ...]]) -> np.ndarray:
        node = storage.getNode(key)
        data = node.getNode("data") if not node.empty() and node.isMap() else node
        if node.empty() or data.empty() or not data.isSeq():
            raise RigError(f"{side}.{key}", "missing (a ROS camera_info entry with data: [...])")
        return _shaped(f"{side}.{key}", _numbers(data), shapes)

    size = _image_size(storage)
    k = entry("camera_matrix", [(3, 3)])
    _camera(k, f"{side}.camera_matrix")
    d = entry("distortion_coefficients", [(n,) for n in DISTORTION_LENGTHS])
    r = entry("rectification_matrix", [(3, 3)])
    p = entry("projection_matrix", [(3, 4)])
    return size, k, d, r, p


def _ros_rig(left: cv2.FileStorage, right: cv2.FileStorage) -> StereoRig:
    size, k1, d1, r1, p1 = _ros_camera(left, "left")
    right_size, k2, d2, r2, p2 = _ros_camera(right, "right")
    if right_size != size:
        raise RigError(
            "image_size",
            f"the left camera_info is for {size[0]}x{size[1]}, the right for {right_size[0]}x{right_size[1]}",
        )
    if not p2[0, 3] < 0:
        raise RigError(
            "right.projection_matrix", "P[0][3] must be -fx * baseline < 0 (the right camera of a rectified pair)"
        )
    return StereoRig(size, k1, d1, k2, d2, r1, r2, p1, p2)
