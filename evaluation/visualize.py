"""Per-pair evaluation sheets and line plots (PNG-ready uint8 RGB images); colour maps are
`stereo_data.visualize`'s."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from crestereo_pp.stereo_data.readers import StereoSample
from crestereo_pp.stereo_data.visualize import UNCERTAINTY_COLORMAP, colorize

from .metrics import Sparsification

ERROR_SCALE_PX = 8.0
"""Absolute disparity error (px) shown at the top of the error colour map on every sheet."""

PANEL_WIDTH = 480
"""Width in pixels of one panel of a sheet (images are resized to it, aspect kept)."""

TITLE_HEIGHT = 24


@dataclass(frozen=True)
class Panel:
    """One titled image of a sheet: `image` is uint8 HxWx3 RGB."""

    title: str
    image: np.ndarray


def disparity_panels(
    name: str,
    prediction: np.ndarray,
    ground_truth: np.ndarray,
    valid: np.ndarray,
    disparity_max: float,
) -> list[Panel]:
    """The prediction and its |error| map for one method.

    prediction, ground_truth: float HxW (px); valid: bool HxW. Disparity is coloured on the
    fixed scale [0, disparity_max]; the error on [0, ERROR_SCALE_PX]; no-ground-truth pixels black.
    """
    error = np.where(valid & np.isfinite(ground_truth), np.abs(prediction - ground_truth), np.inf)
    return [
        Panel(f"{name} disparity", colorize(prediction, 0.0, disparity_max)),
        Panel(f"{name} |error| 0-{ERROR_SCALE_PX:g} px", colorize(error, 0.0, ERROR_SCALE_PX, cv2.COLORMAP_PLASMA)),
    ]


def compose_sheet(rows: list[list[Panel]]) -> np.ndarray:
    """Lay titled panels out in a grid, one list per row (short rows padded white).

    Returns uint8 HxWx3 RGB; every panel is resized to PANEL_WIDTH, aspect kept.
    """
    columns = max(len(row) for row in rows)
    tile_rows = []
    for row in rows:
        tiles = [_titled_tile(panel) for panel in row]
        tile_height = max(tile.shape[0] for tile in tiles)
        tiles = [np.pad(t, ((0, tile_height - t.shape[0]), (0, 0), (0, 0)), constant_values=255) for t in tiles]
        tiles += [np.full((tile_height, PANEL_WIDTH, 3), 255, np.uint8)] * (columns - len(tiles))
        tile_rows.append(np.concatenate(tiles, axis=1))
    return np.concatenate(tile_rows, axis=0)


def _titled_tile(panel: Panel) -> np.ndarray:
    """The panel's image resized to PANEL_WIDTH wide, under a white strip with its title."""
    height, width = panel.image.shape[:2]
    panel_height = max(1, round(height * PANEL_WIDTH / width))
    image = cv2.resize(panel.image, (PANEL_WIDTH, panel_height), interpolation=cv2.INTER_AREA)
    title = np.full((TITLE_HEIGHT, PANEL_WIDTH, 3), 255, np.uint8)
    cv2.putText(title, panel.title, (6, TITLE_HEIGHT - 7), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([title, image], axis=0)


def _span(values: np.ndarray) -> tuple[float, float]:
    """(min, max) of `values`, widened to (v, v + 1) when they are all equal."""
    low, high = float(values.min()), float(values.max())
    return (low, high) if high > low else (low, low + 1.0)


def line_plot(
    series: Mapping[str, tuple[Sequence[float], Sequence[float]]],
    x_label: str,
    y_label: str,
    log_y: bool = False,
    size: tuple[int, int] = (900, 500),
) -> np.ndarray:
    """Named (x, y) line series drawn on one pair of axes: uint8 RGB image of `size` (w, h)."""
    (width, height), margin_left, margin_bottom, margin = size, 80, 50, 20
    canvas = np.full((height, width, 3), 255, np.uint8)
    plot_w, plot_h = width - margin_left - margin, height - margin_bottom - margin
    points = [
        (x, y)
        for xs, ys in series.values()
        for x, y in zip(xs, ys, strict=True)
        if math.isfinite(y) and (y > 0 or not log_y)
    ]
    if not points:
        return canvas
    transform = np.log10 if log_y else np.asarray
    x_all = np.array([p[0] for p in points], dtype=np.float64)
    y_all = transform(np.array([p[1] for p in points], dtype=np.float64))
    x_low, x_high = _span(x_all)
    y_low, y_high = _span(y_all)

    def to_pixels(xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        px = margin_left + (xs - x_low) / (x_high - x_low) * plot_w
        py = margin + (1.0 - (ys - y_low) / (y_high - y_low)) * plot_h
        return np.stack([px, py], axis=1).round().astype(np.int32)

    black, grey = (0, 0, 0), (200, 200, 200)
    font = cv2.FONT_HERSHEY_SIMPLEX
    for i in range(6):
        fraction = i / 5
        x_pixel = int(margin_left + fraction * plot_w)
        y_pixel = int(margin + (1 - fraction) * plot_h)
        cv2.line(canvas, (x_pixel, margin), (x_pixel, margin + plot_h), grey, 1)
        cv2.line(canvas, (margin_left, y_pixel), (margin_left + plot_w, y_pixel), grey, 1)
        x_value = x_low + fraction * (x_high - x_low)
        y_value = y_low + fraction * (y_high - y_low)
        cv2.putText(
            canvas, f"{x_value:.4g}", (x_pixel - 20, height - margin_bottom + 20), font, 0.4, black, 1, cv2.LINE_AA
        )
        y_text = f"{10**y_value:.3g}" if log_y else f"{y_value:.3g}"
        cv2.putText(canvas, y_text, (5, y_pixel + 4), font, 0.4, black, 1, cv2.LINE_AA)
    cv2.rectangle(canvas, (margin_left, margin), (margin_left + plot_w, margin + plot_h), black, 1)
    cv2.putText(canvas, x_label, (margin_left + plot_w // 2 - 30, height - 8), font, 0.5, black, 1, cv2.LINE_AA)
    cv2.putText(canvas, y_label, (margin_left + 5, margin - 5), font, 0.5, black, 1, cv2.LINE_AA)

    colors = [(30, 80, 200), (220, 40, 40), (40, 160, 40), (160, 40, 160)]  # RGB
    for number, (name, (xs, ys)) in enumerate(series.items()):
        color = colors[number % len(colors)]
        x_values, y_values = np.asarray(xs, np.float64), np.asarray(ys, np.float64)
        keep = np.isfinite(y_values) & ((y_values > 0) if log_y else True)
        if keep.any():
            line = to_pixels(x_values[keep], transform(y_values[keep]))
            cv2.polylines(canvas, [line], False, color, 2, cv2.LINE_AA)
        legend_y = margin + 20 + 20 * number
        cv2.line(canvas, (width - 220, legend_y - 4), (width - 195, legend_y - 4), color, 2)
        cv2.putText(canvas, name, (width - 190, legend_y), font, 0.45, black, 1, cv2.LINE_AA)
    return canvas


def evaluation_sheet(
    sample: StereoSample,
    known: np.ndarray,
    uncertainty: np.ndarray,
    disparities: dict[str, np.ndarray],
    curves: dict[str, Sparsification],
) -> np.ndarray:
    """Sheet image (uint8 RGB) of one pair: row 1 left, ground truth, the model's uncertainty;
    then one row per method (disparity, |error|); last, the sparsification curves of `curves`
    with the optimal one. `disparities` maps method -> float HxW px."""
    ground_truth = np.where(known, sample.disparity, np.inf)
    disparity_max = float(ground_truth[known].max())
    rows = [
        [
            Panel(f"{sample.name} left", sample.left),
            Panel(
                f"ground truth 0-{disparity_max:.0f} px (black: unknown)", colorize(ground_truth, 0.0, disparity_max)
            ),
            Panel("uncertainty 0-1", colorize(uncertainty, 0.0, 1.0, UNCERTAINTY_COLORMAP)),
        ]
    ]
    rows += [disparity_panels(name, d, sample.disparity, known, disparity_max) for name, d in disparities.items()]
    rows.append([Panel("sparsification: bad-2 % of the most trusted pixels", sparsification_plot(curves))])
    return compose_sheet(rows)


def sparsification_plot(curves: dict[str, Sparsification]) -> np.ndarray:
    """uint8 RGB plot of each method's sparsification curve (bad-2 % against % removed)."""
    series = {
        f"{name} (AUC/opt {curve.ratio_to_optimal:.2f})": (list(curve.removed_percent), list(curve.bad_percent))
        for name, curve in curves.items()
    }
    return line_plot(series, "% most uncertain pixels removed", "bad-2 % of the rest", size=(720, 360))
