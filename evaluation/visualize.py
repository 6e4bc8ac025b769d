"""Colour maps and per-pair evaluation sheets (PNG-ready uint8 RGB images)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

ERROR_SCALE_PX = 8.0
"""Absolute disparity error (px) shown at the top of the error colour map on every sheet."""

PANEL_WIDTH = 480
"""Width in pixels of one panel of a sheet (images are resized to it, aspect kept)."""

TITLE_HEIGHT = 24


def colorize(values: np.ndarray, vmin: float, vmax: float, colormap: int = cv2.COLORMAP_TURBO) -> np.ndarray:
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
