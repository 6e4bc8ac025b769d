"""What a training run leaves to read: CSV logs and curve PNGs (drawn with OpenCV)."""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np


class CsvLog:
    """An append-only CSV file with a fixed header, one row per call to `append`.

    Opened with `keep_until_step`, an existing file keeps only its rows with step <= that step
    (a resumed run continues the log of the run it resumes, dropping rows logged after the
    checkpoint it resumes from); without it, any existing file is replaced.
    """

    def __init__(self, path: Path, columns: Sequence[str], keep_until_step: int | None = None) -> None:
        if columns[0] != "step":
            raise ValueError("the first column of a training log is 'step'")
        self.path = path
        self.columns = list(columns)
        kept = [r for r in read_csv(path) if int(r["step"]) <= keep_until_step] if keep_until_step is not None else []
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open("w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=self.columns)
            writer.writeheader()
            writer.writerows(kept)

    def append(self, row: dict[str, float | int]) -> None:
        with self.path.open("a", newline="") as f:
            csv.DictWriter(f, fieldnames=self.columns).writerow({k: _format(v) for k, v in row.items()})


def read_csv(path: Path) -> list[dict[str, str]]:
    """Rows of a CSV file with a header, as dicts of strings; [] when the file does not exist."""
    if not path.is_file():
        return []
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def _format(value: float | int) -> str:
    return repr(value) if isinstance(value, float) else str(value)


def _span(values: np.ndarray) -> tuple[float, float]:
    """(min, max) of `values`, widened to (v, v + 1) when they are all equal."""
    low, high = float(values.min()), float(values.max())
    return (low, high) if high > low else (low, low + 1.0)


def plot_curves(
    series: dict[str, tuple[Sequence[float], Sequence[float]]],
    path: Path,
    x_label: str,
    y_label: str,
    log_y: bool = False,
) -> None:
    """Draw named (x, y) line series on one pair of axes and write them to a PNG at `path`."""
    width, height, margin_left, margin_bottom, margin = 900, 500, 80, 50, 20
    canvas = np.full((height, width, 3), 255, np.uint8)
    plot_w, plot_h = width - margin_left - margin, height - margin_bottom - margin
    points = [
        (x, y)
        for xs, ys in series.values()
        for x, y in zip(xs, ys, strict=True)
        if math.isfinite(y) and (y > 0 or not log_y)
    ]
    if not points:
        cv2.imwrite(str(path), canvas)
        return
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

    colours = [(200, 80, 30), (40, 40, 220), (40, 160, 40), (160, 40, 160)]  # BGR
    for number, (name, (xs, ys)) in enumerate(series.items()):
        colour = colours[number % len(colours)]
        x_values, y_values = np.asarray(xs, np.float64), np.asarray(ys, np.float64)
        keep = np.isfinite(y_values) & ((y_values > 0) if log_y else True)
        if keep.any():
            line = to_pixels(x_values[keep], transform(y_values[keep]))
            cv2.polylines(canvas, [line], False, colour, 2, cv2.LINE_AA)
        legend_y = margin + 20 + 20 * number
        cv2.line(canvas, (width - 220, legend_y - 4), (width - 195, legend_y - 4), colour, 2)
        cv2.putText(canvas, name, (width - 190, legend_y), font, 0.45, black, 1, cv2.LINE_AA)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), canvas)
