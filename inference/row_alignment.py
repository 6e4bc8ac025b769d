"""The right image's rows put onto the left image's (``InferenceOptions.align_rows``).

A rectified pair's matches lie on the same row; real rectifications leave a residual of a few
tenths of a pixel and more (dev pairs of KITTI: up to 0.8 px at a corner), and a camera
whose calibration has drifted, whole pixels. The network and SGBM both lose much of their
precision to it (lite's dev bad-2 7.96 -> 18.2 % at 1 px, 38.2 % at 2 px). So the residual is
measured on the pair itself: corners of the left image tracked into the right one (pyramidal
Lucas-Kanade, each track checked by tracking it back), their vertical offsets fitted as a plane
over the right image (a shift, a tilt across, a tilt down: what a residual rotation or focal
length mismatch leaves), and the right image resampled onto the left's rows where the plane is
off by more than MIN_OFFSET_PX anywhere. Elsewhere the pair is computed as it is. Pairs given as
arrays only: tensors on a device are computed as given, so that nothing crosses to the host before
the network (``predict_pairs``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .sgbm import host_rgb8

MIN_OFFSET_PX = 0.25
"""Rows off by less than this everywhere are left as they are (px)."""

MIN_TRACKS = 30
"""Fewest tracked corners that agree with the fitted plane for it to be trusted."""

TILT_PRIOR_PX = 0.5
"""One standard deviation of the prior on each tilt (`RowOffset.across_px`, `down_px`: dy's change
from one edge of the image to the other): a real rig's residual tilts stay within about 0.7 px
(the dev pairs)."""

_CORNERS = 1000
_WINDOW_PX = 21
MIN_ROWS = 2 * _WINDOW_PX
"""Fewest rows of a pair whose offset is measured: two tracking windows."""
_LEVELS = 5  # a window of 21 px at 1/32 follows disparities of several hundred pixels
_STOP = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
_RESAMPLED_AS_IS = {
    np.dtype(np.uint8),
    np.dtype(np.uint16),
    np.dtype(np.int16),
    np.dtype(np.float32),
    np.dtype(np.float64),
}
_ROUND_TRIP_PX = 0.5  # a track that does not come back within this of its corner is dropped


@dataclass(frozen=True)
class RowOffset:
    """Where the right image's rows lie against the left's: the match of a left pixel lies
    ``dy`` px lower in the right image (negative: higher) than its row, with

        dy(x, y) = centre_px + across_px * (x / W - 1/2) + down_px * (y / H - 1/2)

    at right-image pixel (x, y) of a W x H image. tracks: the corners the plane was fitted to."""

    centre_px: float
    across_px: float
    down_px: float
    tracks: int

    @property
    def aligned(self) -> bool:
        """Whether ``align_rows`` resamples a right image so far off (MIN_OFFSET_PX somewhere)."""
        return self.largest_px >= MIN_OFFSET_PX

    @property
    def largest_px(self) -> float:
        """The largest |dy| over the image (at one of its corners)."""
        return abs(self.centre_px) + 0.5 * abs(self.across_px) + 0.5 * abs(self.down_px)

    def offsets(self, height: int, width: int) -> np.ndarray:
        """dy at every pixel of the right image: float32 HxW, px."""
        across = (np.arange(width, dtype=np.float32) / width - 0.5) * self.across_px
        down = (np.arange(height, dtype=np.float32) / height - 0.5) * self.down_px
        return (self.centre_px + down[:, None] + across[None, :]).astype(np.float32)


def measure_row_offset(left: np.ndarray, right: np.ndarray) -> RowOffset | None:
    """The right image's row offset against the left's (arrays as ``as_image_batch`` reads them),
    or None where too few corners can be tracked to say (a pair without texture), or the pair is
    under MIN_ROWS rows tall (its tracks' windows reach past its top and bottom)."""
    if left.shape[0] < MIN_ROWS:
        return None
    grey_left, grey_right = (cv2.cvtColor(host_rgb8(image), cv2.COLOR_RGB2GRAY) for image in (left, right))
    corners = cv2.goodFeaturesToTrack(grey_left, _CORNERS, 0.01, 7, blockSize=7)
    if corners is None or len(corners) < MIN_TRACKS:
        return None
    there, found = _track(grey_left, grey_right, corners)
    back, found_back = _track(grey_right, grey_left, there)
    start, end = corners[:, 0], there[:, 0]
    kept = (found[:, 0] == 1) & (found_back[:, 0] == 1) & (np.linalg.norm(back[:, 0] - start, axis=1) < _ROUND_TRIP_PX)
    kept &= start[:, 0] - end[:, 0] > -1.0  # a match lies at or left of its corner (positive disparity)
    start, end = start[kept], end[kept]
    if len(end) < MIN_TRACKS:
        return None
    height, width = grey_right.shape
    dy = (end[:, 1] - start[:, 1]).astype(np.float64)
    plane = np.stack([np.ones(len(end)), end[:, 0] / width - 0.5, end[:, 1] / height - 0.5], axis=1)
    inliers = np.abs(dy - np.median(dy)) < 1.0
    for _ in range(5):  # refit on the tracks that agree with the plane (3 robust sigmas, at least 0.3 px)
        if inliers.sum() < MIN_TRACKS:
            return None
        coefficients = _fit_plane(plane[inliers], dy[inliers])
        residuals = np.abs(dy - plane @ coefficients)
        inliers = residuals < max(0.3, 3 * 1.4826 * float(np.median(residuals[inliers])))
    if inliers.sum() < MIN_TRACKS or inliers.mean() < 0.5:
        return None
    centre, across, down = (float(c) for c in coefficients)
    return RowOffset(centre, across, down, int(inliers.sum()))


def _fit_plane(plane: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """(shift, tilt across, tilt down) px of the offsets `dy` (N,) at the tracks' N x 3 design
    `plane`: least squares with a Gaussian prior of TILT_PRIOR_PX on each tilt, weighed against
    the tracks' scatter about the plain fit. Tracks spread over the image hardly feel it; tracks
    in one part of it carry their tilts to its corners as guesses, which it draws towards none."""
    plain = np.linalg.lstsq(plane, dy, rcond=None)[0]
    scatter = max(float(np.sum((dy - plane @ plain) ** 2)) / max(len(dy) - 3, 1), 1e-4)  # px^2
    prior = np.diag([0.0, 1.0, 1.0]) * scatter / TILT_PRIOR_PX**2
    return np.linalg.solve(plane.T @ plane + prior, plane.T @ dy)


def _track(source: np.ndarray, target: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where `points` (N x 1 x 2, x and y px) of grey image `source` lie in `target`, and whether
    each was found (N x 1, 1 = found)."""
    moved, found, _ = cv2.calcOpticalFlowPyrLK(
        source, target, points, None, winSize=(_WINDOW_PX, _WINDOW_PX), maxLevel=_LEVELS, criteria=_STOP
    )
    return moved, found


def align_rows(left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, RowOffset | None]:
    """``right`` (an array, as ``as_image_batch`` reads it) put onto ``left``'s rows, and the
    offset measured (``measure_row_offset``; None where the pair has too little texture to say).
    Where the offset reaches MIN_OFFSET_PX somewhere, the image is resampled (bilinear, edges
    replicated): an array of its channels, and of its dtype where OpenCV resamples that (else
    float32, values as they were). Else ``right`` itself."""
    offset = measure_row_offset(left, right)
    if offset is None or not offset.aligned:
        return right, offset
    height, width = right.shape[:2]
    columns, rows = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
    rows += offset.offsets(height, width)
    source = right if right.dtype in _RESAMPLED_AS_IS else right.astype(np.float32)  # int32/64, float16, bool
    aligned = cv2.remap(np.ascontiguousarray(source), columns, rows, cv2.INTER_LINEAR, None, cv2.BORDER_REPLICATE)
    if right.ndim == 3 and aligned.ndim == 2:  # OpenCV drops a lone channel
        aligned = aligned[..., None]
    return aligned, offset
