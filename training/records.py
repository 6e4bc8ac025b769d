"""What a training run leaves to read: CSV logs and curve PNGs (drawn with OpenCV)."""

from __future__ import annotations

import csv
from collections.abc import Mapping, Sequence
from pathlib import Path

from crestereo_pp.evaluation.visualize import line_plot
from crestereo_pp.stereo_data.formats import encode_png


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


def plot_curves(
    series: Mapping[str, tuple[Sequence[float], Sequence[float]]],
    path: Path,
    x_label: str,
    y_label: str,
    log_y: bool = False,
) -> None:
    """Draw named (x, y) line series on one pair of axes (`line_plot`) into a PNG at `path`."""
    path.parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_bytes(encode_png(line_plot(series, x_label, y_label, log_y)))
