"""A calibrated stereo camera: read its calibration, rectify its pairs, and bring maps back.

    rig = read_rig("stereo.yaml")          # OpenCV's K1, D1, K2, D2, R, T; or two ROS camera_info files
    rectifier = Rectifier(rig)                        # maps computed once for the rig's image size
    left_r, right_r = rectifier.rectify(left, right)  # rectified pair: matches lie on the same row
    disparity, uncertainty = predictor.predict(left_r, right_r)
    focal_baseline = rectifier.focal_baseline         # focal length, baseline, principal point (metres)
    disparity_original = rectifier.to_original(disparity)  # in the original left image's pixels
    depth_original = rectifier.to_original_depth(depth)    # metres along the original camera's axis

Conventions are OpenCV's: K is the 3x3 camera matrix, D the distortion coefficients (4, 5, 8, 12
or 14), and R, T take a point from the left camera's frame into the right camera's (so a right
camera to the right of the left one has T[0] < 0); T's unit is the depth's unit (metres here).
A ROS pair of ``sensor_msgs/CameraInfo`` files carries its rectification already (R and P per
camera): it is used as given. Disparity is in rectified pixels, positive: left x matches right
x - d on the same rectified row. A rig is refused (RigError naming the entry) unless its images
are 1 to MAX_IMAGE_SIDE px a side, R (ROS: each rectification matrix) is a rotation by at most
MAX_TURN_DEGREES, and its focal length x baseline is within MIN_FOCAL_BASELINE-MAX_FOCAL_BASELINE, the
bounds of a query's focal_px x baseline_m. Calibrations that OpenCV would rectify but that no real
camera has are refused too, as the mistakes they usually are: a focal length outside
MIN_FOCAL_SIDES-MAX_FOCAL_SIDES times the image's longer side, a rectification that magnifies or
shrinks an image more than MAX_RECTIFIED_ZOOM times (distortion coefficients far off), and a
baseline over MAX_BASELINE_M (a calibration in millimetres read as metres) or under MIN_BASELINE_M
(two cameras in one place).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path

import cv2
import numpy as np

from .calibration_files import RigError, Value, parse_entries
from .pointcloud import FocalBaseline

__all__ = [
    "MAX_FOCAL_BASELINE",
    "MAX_IMAGE_SIDE",
    "MIN_FOCAL_BASELINE",
    "MAX_TURN_DEGREES",
    "MAX_FOCAL_SIDES",
    "MIN_FOCAL_SIDES",
    "MAX_RECTIFIED_ZOOM",
    "MAX_BASELINE_M",
    "MIN_BASELINE_M",
    "RigError",
    "StereoRig",
    "Rectifier",
    "read_rig",
    "parse_rig",
    "focal_baseline_problem",
]

DISTORTION_LENGTHS = (4, 5, 8, 12, 14)
MAX_IMAGE_SIDE = 32766
"""Widest and highest image a rig may be for: OpenCV's remap (rectification) takes sides under 32767 px."""
MAX_FOCAL_BASELINE = float(np.finfo(np.float32).max)
"""Largest focal length (px) x baseline (m), a rig's or a query's: depth f B / d is float32."""
MIN_FOCAL_BASELINE = float(np.finfo(np.float32).tiny) * MAX_IMAGE_SIDE
"""Smallest focal length (px) x baseline (m), a rig's or a query's: depth f B / d stays a normal
float32 above 0 at the widest disparity (4e-34; below, every depth would read 0 m)."""
MAX_TURN_DEGREES = 30.0
"""Largest turn of the right camera against the left (OpenCV's R), or of a camera into its rectified
frame (ROS's rectification matrix): beyond it the rectified views barely overlap (none at 90)."""
MAX_FOCAL_SIDES = 100.0
"""Longest focal length (px) a camera may have, in multiples of its image's longer side: a field of
view of 0.57 degrees; longer ones are focal lengths in another unit, or typos."""
MIN_FOCAL_SIDES = 0.05
"""Shortest focal length (px), in multiples of the image's longer side: a field of view of 169
degrees, near the 180 where a pinhole camera model ends."""
MAX_RECTIFIED_ZOOM = 4.0
"""Most a rectification may magnify (or shrink) an image, as the rectified focal length against
the camera's own: real rigs stay within about 1.5; distortion coefficients far off make OpenCV crop
the rectified view to a sliver (D1 = [50, -80, 0, 0, 0] on a 300 px camera: 9x)."""
MAX_BASELINE_M = 10.0
"""Longest baseline (m) a rig may have: a calibration made with its chessboard measured in
millimetres has T in millimetres, and read as metres every depth would be 1000 times too large."""
MIN_BASELINE_M = 1e-4
"""Shortest baseline (m) a rig may have: a tenth of a millimetre, far below any stereo camera's
(phones' a centimetre or so); shorter ones are cameras that coincide, or T in another unit."""


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
        distortion = [(n,) for n in DISTORTION_LENGTHS]
        rig = StereoRig(
            _pixels(float(width), float(height)),
            array("k1", [(3, 3)]),
            array("d1", distortion),
            array("k2", [(3, 3)]),
            array("d2", distortion),
            array("r1", [(3, 3)]),
            array("r2", [(3, 3)]),
            array("p1", [(3, 4)]),
            array("p2", [(3, 4)]),
        )
        return _checked(rig, "calibration")


def read_rig(paths: str | Path | Sequence[str | Path]) -> StereoRig:
    """The rig of one OpenCV calibration file (YAML or JSON as ``cv2.FileStorage`` writes it) or
    of two ROS ``camera_info`` YAML files (left, then right), read strictly by
    `stereo_data.calibration_files` (never by OpenCV's parser). RigError where it is unusable."""
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
        entries = parse_entries(text, "calibration")
        if "camera_matrix" in entries and "K1" not in entries:
            raise RigError(
                "calibration",
                "this is one ROS camera_info, which describes one camera: give the left camera's and the right "
                "camera's (two files, left first)",
            )
        return _opencv_rig(entries)
    return _ros_rig(
        parse_entries(text, "left camera_info", "left."), parse_entries(right_text, "right camera_info", "right.")
    )


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
        # Which of them land on the rectified image (within half a pixel of its outer pixels' centres).
        back_x, back_y = self._back[..., 0], self._back[..., 1]
        self._inside = (back_x >= -0.5) & (back_x <= width - 0.5) & (back_y >= -0.5) & (back_y <= height - 0.5)

    @property
    def focal_baseline(self) -> FocalBaseline:
        """Focal length, baseline and principal point of the rectified left camera."""
        p1 = self.rig.p1
        return FocalBaseline(self.rig.focal_px, self.rig.baseline, float(p1[0, 2]), float(p1[1, 2]))

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
        counterpart (or its neighbours there are not finite: +inf disparity stays unknown). One that
        lands within half a pixel of the rectified image's edge takes the edge's values (under an
        identity calibration, the last row and column land on themselves)."""
        back_x, back_y = self._back[..., 0], self._back[..., 1]
        resampled = cv2.remap(
            rectified.astype(np.float32), back_x, back_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
        known = self._inside & np.isfinite(resampled)
        return np.where(known, resampled, np.float32(missing)).astype(np.float32)

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


def _entry(entries: dict[str, Value], prefix: str, key: str, shapes: Sequence[tuple[int, ...]]) -> np.ndarray:
    """A matrix or list entry as float64 of one of `shapes` (flat lengths match any layout)."""
    value = entries.get(key)
    if value is None:
        raise RigError(prefix + key, "missing")
    if not isinstance(value, np.ndarray):
        raise RigError(prefix + key, f"expected a matrix or a list of numbers, got {str(value)[:32]!r}")
    return _shaped(prefix + key, value.reshape(-1), shapes)


def _shaped(key: str, value: np.ndarray, shapes: Sequence[tuple[int, ...]]) -> np.ndarray:
    for shape in shapes:
        if value.size == int(np.prod(shape)):
            value = value.reshape(shape)
            if not np.isfinite(value).all():
                raise RigError(key, "holds a value that is not a finite number")
            return value
    wanted = " or ".join("x".join(map(str, shape)) for shape in shapes)
    raise RigError(key, f"expected {wanted} values, got {value.size}")


def _image_size(entries: dict[str, Value]) -> tuple[int, int]:
    if "image_size" in entries:
        width, height = _entry(entries, "", "image_size", [(2,)]).tolist()
        return _pixels(width, height)
    width, height = (entries.get(key) for key in ("image_width", "image_height"))
    if width is None or height is None:
        raise RigError("image_size", "missing: give image_size [width, height], or image_width and image_height")
    if not (isinstance(width, float) and isinstance(height, float)):
        raise RigError("image_size", f"image_width and image_height are numbers, got {width!r:.32} and {height!r:.32}")
    return _pixels(width, height)


def _pixels(width: float, height: float) -> tuple[int, int]:
    """An image size in whole pixels, from 1 to MAX_IMAGE_SIDE a side."""
    if not all(1 <= side <= MAX_IMAGE_SIDE and side.is_integer() for side in (width, height)):
        raise RigError(
            "image_size", f"expected whole numbers of pixels from 1 to {MAX_IMAGE_SIDE}, got {width:g}x{height:g}"
        )
    return int(width), int(height)


def _camera(k: np.ndarray, k_name: str, size: tuple[int, int]) -> None:
    """RigError unless `k` is a camera matrix whose focal lengths (px) are within MIN_FOCAL_SIDES to
    MAX_FOCAL_SIDES times the longer side of the `size` (width, height) images."""
    if not (k[0, 0] > 0 and k[1, 1] > 0 and np.allclose(k[2], (0.0, 0.0, 1.0))):
        raise RigError(k_name, "not a camera matrix: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
    side = max(size)
    for focal in (k[0, 0], k[1, 1]):
        if not MIN_FOCAL_SIDES * side <= focal <= MAX_FOCAL_SIDES * side:
            raise RigError(
                k_name,
                f"a focal length of {focal:.6g} px for {size[0]}x{size[1]} images: expected "
                f"{MIN_FOCAL_SIDES:g} to {MAX_FOCAL_SIDES:g} times the longer side ({MIN_FOCAL_SIDES * side:g}-"
                f"{MAX_FOCAL_SIDES * side:g} px, a field of view of 169 to 0.57 degrees); focal lengths are in pixels",
            )


def _rotation(field: str, matrix: np.ndarray, turned: str) -> None:
    """RigError unless `matrix` is a rotation (orthonormal to 1e-3, determinant +1) by at most
    MAX_TURN_DEGREES; `turned` says what it turns, for the message."""
    if not (
        np.abs(matrix).max() <= 1.001  # first: larger entries would overflow the product
        and np.allclose(matrix @ matrix.T, np.eye(3), atol=1e-3)
        and np.linalg.det(matrix) > 0
    ):
        raise RigError(field, "not a rotation matrix (orthonormal, determinant 1)")
    degrees = math.degrees(math.acos(min(1.0, max(-1.0, (float(np.trace(matrix)) - 1) / 2))))
    if degrees > MAX_TURN_DEGREES:
        raise RigError(
            field,
            f"{turned} by {degrees:.1f} degrees; at most {MAX_TURN_DEGREES:g} (beyond, the rectified views "
            "barely overlap)",
        )


def _checked(rig: StereoRig, field: str) -> StereoRig:
    """`rig`, once its rectified cameras give depth as a query's focal_px and baseline_m do (both
    positive, their product within MIN_FOCAL_BASELINE-MAX_FOCAL_BASELINE: ``focal_baseline_problem``),
    its baseline is within MIN_BASELINE_M-MAX_BASELINE_M and its rectification magnifies neither camera's image
    more than MAX_RECTIFIED_ZOOM times nor shrinks it so. `field` names the baseline's entry."""
    problem = focal_baseline_problem(rig.focal_px, rig.baseline, "focal length x baseline")
    if problem is not None:
        raise RigError(field, problem)
    if rig.baseline < MIN_BASELINE_M:
        raise RigError(
            field,
            f"a baseline of {rig.baseline:.6g} m; at least {MIN_BASELINE_M:g} m: the two cameras are as good as "
            "one (T is in metres)",
        )
    if rig.baseline > MAX_BASELINE_M:
        raise RigError(
            field,
            f"a baseline of {rig.baseline:.6g} m; at most {MAX_BASELINE_M:g} m: T is in metres (a calibration made "
            "with the chessboard's squares in millimetres has T in millimetres: divide it by 1000)",
        )
    for side, k, p in (("left", rig.k1, rig.p1), ("right", rig.k2, rig.p2)):
        zoom = float(p[0, 0] / k[0, 0])
        if not 1 / MAX_RECTIFIED_ZOOM <= zoom <= MAX_RECTIFIED_ZOOM:
            raise RigError(
                "calibration",
                f"rectifying would scale the {side} image {zoom:.3g} times (focal length {k[0, 0]:.6g} px -> "
                f"{p[0, 0]:.6g} px); real rigs stay within about 1.5: check the distortion coefficients and "
                "camera matrices",
            )
    return rig


def focal_baseline_problem(focal_px: float, baseline: float, name: str) -> str | None:
    """Why depth f B / d cannot be float32 for this focal length (px) and baseline (m), the
    product called `name` in the message: either is not positive, or the product is out of
    MIN_FOCAL_BASELINE-MAX_FOCAL_BASELINE; None where it can."""
    if not (focal_px > 0 and baseline > 0):
        return f"the focal length and baseline ({name}) must be positive, got {focal_px:.4g} and {baseline:.4g}"
    product = focal_px * baseline
    if product > MAX_FOCAL_BASELINE:
        return f"{name} is {product:.4g}, more than {MAX_FOCAL_BASELINE:.4g} (depth is float32)"
    if product < MIN_FOCAL_BASELINE:
        return f"{name} is {product:.4g}, less than {MIN_FOCAL_BASELINE:.4g} (depth is float32: every depth would be 0)"
    return None


def _opencv_rig(entries: dict[str, Value]) -> StereoRig:
    size = _image_size(entries)
    k1, k2 = (_entry(entries, "", key, [(3, 3)]) for key in ("K1", "K2"))
    d1, d2 = (_entry(entries, "", key, [(n,) for n in DISTORTION_LENGTHS]) for key in ("D1", "D2"))
    _camera(k1, "K1", size)
    _camera(k2, "K2", size)
    rotation = _entry(entries, "", "R", [(3, 3), (3,)])
    if rotation.shape == (3,):
        rotation = cv2.Rodrigues(rotation)[0]  # a rotation vector
    _rotation("R", rotation, "the right camera is turned against the left")
    translation = _entry(entries, "", "T", [(3,)])
    with np.errstate(over="ignore"):  # a length past float64 is refused below, with focal x baseline
        length = np.linalg.norm(translation)
    if not length > 0:  # as OpenCV measures it: below about 1e-160 m the square underflows to 0
        raise RigError("T", "the baseline is zero: the two cameras are at one place")
    if abs(translation[0]) < 2 * max(abs(translation[1]), abs(translation[2])):
        raise RigError(
            "T", f"the cameras are not side by side ({translation.tolist()}): this matcher needs a horizontal baseline"
        )
    if translation[0] > 0:
        raise RigError(
            "T", "the right camera is to the left of the left one (T[0] > 0): swap the images and the cameras"
        )
    try:
        r1, r2, p1, p2, *_ = cv2.stereoRectify(
            k1, d1, k2, d2, size, rotation, translation.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0
        )
    except cv2.error:
        raise RigError("calibration", "OpenCV cannot rectify these cameras") from None
    if not (np.isfinite(p1).all() and np.isfinite(p2).all()):
        raise RigError("calibration", "OpenCV cannot rectify these cameras")
    return _checked(StereoRig(size, k1, d1, k2, d2, r1, r2, p1, p2), "T")


RosCamera = tuple[tuple[int, int], np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""image size, K, D, rectification R, projection P of one ROS camera_info."""


def _ros_camera(entries: dict[str, Value], side: str) -> RosCamera:
    prefix = f"{side}."
    size = _image_size(entries)
    k = _entry(entries, prefix, "camera_matrix", [(3, 3)])
    _camera(k, f"{prefix}camera_matrix", size)
    d = _entry(entries, prefix, "distortion_coefficients", [(n,) for n in DISTORTION_LENGTHS])
    r = _entry(entries, prefix, "rectification_matrix", [(3, 3)])
    _rotation(f"{prefix}rectification_matrix", r, "the rectification turns the camera")
    p = _entry(entries, prefix, "projection_matrix", [(3, 4)])
    _camera(p[:, :3], f"{prefix}projection_matrix", size)
    return size, k, d, r, p


def _ros_rig(left: dict[str, Value], right: dict[str, Value]) -> StereoRig:
    size, k1, d1, r1, p1 = _ros_camera(left, "left")
    right_size, k2, d2, r2, p2 = _ros_camera(right, "right")
    if right_size != size:
        raise RigError(
            "image_size",
            f"the left camera_info is for {size[0]}x{size[1]}, the right for {right_size[0]}x{right_size[1]}",
        )
    if p2[0, 3] >= 0 > p1[0, 3]:  # a right camera's P[0][3] is -fx x baseline, a left camera's 0
        raise RigError(
            "calibration",
            f"the files look swapped: the first camera_info is a right camera's (projection_matrix P[0][3] = "
            f"{p1[0, 3]:.4g}, -fx x baseline) and the second a left camera's (P[0][3] = {p2[0, 3]:.4g}); send the "
            "left camera's first, then the right camera's",
        )
    return _checked(StereoRig(size, k1, d1, k2, d2, r1, r2, p1, p2), "right.projection_matrix")
