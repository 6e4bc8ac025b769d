"""CSV logs continue across resumes; curves are written as PNG images."""

import cv2

from crestereo_pp.training.records import CsvLog, plot_curves, read_csv


def test_a_new_log_replaces_an_old_file(tmp_path):
    path = tmp_path / "log.csv"
    CsvLog(path, ["step", "loss"]).append({"step": 1, "loss": 2.5})
    CsvLog(path, ["step", "loss"])
    assert read_csv(path) == []


def test_a_resumed_log_keeps_rows_up_to_the_checkpoint_step(tmp_path):
    path = tmp_path / "log.csv"
    log = CsvLog(path, ["step", "loss"])
    for step in (1, 2, 3):
        log.append({"step": step, "loss": 1.0 / step})
    CsvLog(path, ["step", "loss"], keep_until_step=2).append({"step": 3, "loss": 9.0})
    assert [(r["step"], float(r["loss"])) for r in read_csv(path)] == [("1", 1.0), ("2", 0.5), ("3", 9.0)]


def test_floats_are_logged_exactly(tmp_path):
    path = tmp_path / "log.csv"
    CsvLog(path, ["step", "loss"]).append({"step": 1, "loss": 0.1 + 0.2})
    assert float(read_csv(path)[0]["loss"]) == 0.1 + 0.2


def test_curves_are_drawn_to_a_png(tmp_path):
    path = tmp_path / "curve.png"
    plot_curves(
        {"loss": ([1, 2, 3], [3.0, 2.0, 1.5]), "epe": ([1, 2, 3], [2.0, 1.0, float("nan")])},
        path,
        "step",
        "px",
        log_y=True,
    )
    image = cv2.imread(str(path))
    assert image is not None and image.shape == (500, 900, 3) and image.min() < 128
