"""Encoding result maps for the response formats of `POST /disparity`."""

from __future__ import annotations

import base64
import io

import cv2
import numpy as np

from stereo_data.visualize import preview

from service.schemas import EncodedArray

KITTI_SCALE = 256.0  # KITTI 16-bit PNG: value = round(map x 256), 0 = invalid
UNCERTAINTY_SCALE = 65535.0


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


def encode_png16(values: np.ndarray, scale: float) -> bytes:
    """Single-channel 16-bit PNG of round(values x scale), clipped to 65535; 0 where the value is
    not finite or not positive."""
    valid = np.isfinite(values) & (values > 0)
    scaled = np.where(valid, np.clip(np.rint(values * scale), 1, 65535), 0).astype(np.uint16)
    return _png(scaled)


def encode_preview(disparity: np.ndarray, uncertainty: np.ndarray,
                   disparity_range: tuple[float, float]) -> bytes:
    """RGB PNG (`stereo_data.visualize.preview`): disparity (turbo, over `disparity_range` px)
    left of uncertainty (inferno, 0-1), each with a colour bar that prints its range."""
    return _png(preview(disparity, uncertainty, disparity_range)[:, :, ::-1])  # imencode wants BGR


def _png(image: np.ndarray) -> bytes:
    ok, encoded = cv2.imencode(".png", image)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return encoded.tobytes()
