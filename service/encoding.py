"""Encoding result maps for the response formats of `POST /disparity`."""

from __future__ import annotations

import base64
import io

import numpy as np

from stereo_data.formats import KITTI_SCALE, UNCERTAINTY_SCALE, encode_png, encode_png16
from stereo_data.visualize import preview

from service.schemas import EncodedArray

def depth_from_disparity(disparity: np.ndarray, focal_px: float, baseline_m: float) -> np.ndarray:
    """Metric depth Z = f B / d in metres (float32), +inf where d <= 0."""
    with np.errstate(divide="ignore"):
        depth = np.float32(focal_px * baseline_m) / disparity
    return np.where(disparity > 0, depth, np.inf).astype(np.float32)


def encode_array(values: np.ndarray) -> EncodedArray:
    """float32 little-endian raw bytes, base64."""
    raw = np.ascontiguousarray(values, dtype="<f4").tobytes()
    return EncodedArray(shape=values.shape, data=base64.b64encode(raw).decode("ascii"))


def encode_npz(maps: dict[str, np.ndarray]) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **maps)
    return buffer.getvalue()


def encode_preview(disparity: np.ndarray, uncertainty: np.ndarray,
                   disparity_range: tuple[float, float]) -> bytes:
    """RGB PNG (`stereo_data.visualize.preview`): disparity (turbo, over `disparity_range` px)
    left of uncertainty (inferno, 0-1), each with a colour bar that prints its range."""
    return encode_png(preview(disparity, uncertainty, disparity_range))

