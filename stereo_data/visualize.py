"""Colour pictures of disparity and uncertainty maps: colour maps, robust ranges, colour bars.

Used by the service's `format=png`, `crestereo-pp predict --color` and the evaluation sheets, so
a map looks the same wherever it is drawn. Images are uint8 HxWx3 RGB.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

DISPARITY_COLORMAP = cv2.COLORMAP_TURBO
UNCERTAINTY_COLORMAP = cv2.COLORMAP_INFERNO
BAR_HEIGHT = 30
"""Height in pixels of a colour bar (gradient strip and its labels)."""


def colorize(values: np.ndarray, vmin: float, vmax: float, colormap: int = DISPARITY_COLORMAP) -> np.ndarray:
    """Map a float HxW array to uint8 HxWx3 RGB with a fixed linear scale [vmin, vmax].

    Values outside the scale are clipped; non-finite values are drawn black.
    """
    finite = np.isfinite(values)
    span = max(vmax - vmin, 1e-6)
    scaled = np.clip((np.where(finite, values, vmin) - vmin) / span, 0.0, 1.0)
    bgr = cv2.applyColorMap((scaled * 255.0).round().astype(np.uint8), colormap)
    rgb = bgr[:, :, ::-1].copy()
    rgb[~finite] = 0
    return rgb


def robust_range(values: np.ndarray, low_percentile: float = 1.0, high_percentile: float = 99.0) -> tuple[float, float]:
    """(low, high) percentiles of the finite values, widened to a span of at least 1e-3; (0, 1)
    when there is no finite value. A map's own range without its few outliers: a Middlebury pair
    of 12-53 px then spans the whole colour map, not the bottom quarter of a fixed 0-192."""
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return 0.0, 1.0
    low, high = (float(v) for v in np.percentile(finite, [low_percentile, high_percentile]))
    return (low, high) if high - low >= 1e-3 else (low, low + 1e-3)


def color_scale_problem(
    low: float | None, high: float | None, names: tuple[str, str] = ("color_min", "color_max")
) -> str | None:
    """Why a colour scale from `low` to `high` (either None: the map's own) cannot be drawn, the
    two called `names` in the message: an end that is not a finite number, or the top not above
    the bottom; None where it can."""
    for name, end in zip(names, (low, high), strict=True):
        if end is not None and not math.isfinite(end):
            return f"{name} must be a finite number, got {end:g}"
    if low is not None and high is not None and high <= low:
        return f"{names[1]} ({high:g}) must be above {names[0]} ({low:g})"
    return None


def scale_range(values: np.ndarray, low: float | None = None, high: float | None = None) -> tuple[float, float]:
    """A colour scale for `values`: the given ends, the robust range (`robust_range`) for the
    missing ones; the top is kept above the bottom. ValueError (`color_scale_problem`) when both
    are given the wrong way."""
    problem = color_scale_problem(low, high)
    if problem is not None:
        raise ValueError(problem)
    robust_low, robust_high = robust_range(values)
    low = robust_low if low is None else low
    high = max(robust_high, low + 1e-3) if high is None else high
    return low, high


def color_bar(width: int, vmin: float, vmax: float, colormap: int, label: str) -> np.ndarray:
    """A BAR_HEIGHT x width strip: the colour map from vmin (left) to vmax (right) over the top
    half, and below it `label` with both ends of the scale written out."""
    bar = np.full((BAR_HEIGHT, width, 3), 255, np.uint8)
    gradient = np.linspace(vmin, vmax, max(width, 1), dtype=np.float64)[None, :].repeat(BAR_HEIGHT // 2, 0)
    bar[: BAR_HEIGHT // 2] = colorize(gradient, vmin, vmax, colormap)
    font, scale, black = cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0)
    baseline = BAR_HEIGHT - 4
    cv2.putText(bar, f"{vmin:.3g}", (2, baseline), font, scale, black, 1, cv2.LINE_AA)
    high = f"{vmax:.3g}"
    (text_width, _), _ = cv2.getTextSize(high, font, scale, 1)
    cv2.putText(bar, high, (max(0, width - text_width - 2), baseline), font, scale, black, 1, cv2.LINE_AA)
    (label_width, _), _ = cv2.getTextSize(label, font, scale, 1)
    cv2.putText(bar, label, (max(0, (width - label_width) // 2), baseline), font, scale, black, 1, cv2.LINE_AA)
    return bar


def with_color_bar(values: np.ndarray, vmin: float, vmax: float, colormap: int, label: str) -> np.ndarray:
    """The coloured map with its colour bar beneath it."""
    return np.vstack([colorize(values, vmin, vmax, colormap), color_bar(values.shape[1], vmin, vmax, colormap, label)])


def disparity_picture(disparity: np.ndarray, disparity_range: tuple[float, float]) -> np.ndarray:
    """Disparity coloured (turbo) over `disparity_range` px (see `scale_range`), with its bar."""
    low, high = disparity_range
    return with_color_bar(disparity, low, high, DISPARITY_COLORMAP, "disparity px")


PREVIEW_GAP = 12
"""White pixels between the two pictures of a preview, so that the end labels of their colour bars
stay apart."""


def preview(disparity: np.ndarray, uncertainty: np.ndarray, disparity_range: tuple[float, float]) -> np.ndarray:
    """Disparity (turbo, over `disparity_range` px) left of uncertainty (inferno, 0-1), each with
    a colour bar that prints its range, PREVIEW_GAP white pixels apart."""
    left = disparity_picture(disparity, disparity_range)
    gap = np.full((left.shape[0], PREVIEW_GAP, 3), 255, np.uint8)
    return np.hstack([left, gap, with_color_bar(uncertainty, 0.0, 1.0, UNCERTAINTY_COLORMAP, "uncertainty")])
