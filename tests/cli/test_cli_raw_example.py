"""The shipped raw example (`service/static/examples/raw-320x240`): a raw pair with its OpenCV
calibration, consistent with each other, gives its true depth through `predict --calibration`."""

import importlib.util
from pathlib import Path
from types import ModuleType

import cv2
import numpy as np
import pytest

from crestereo_pp.cli.main import main
from crestereo_pp.cli.prediction import describe_camera
from crestereo_pp.stereo_data.formats import read_pfm
from crestereo_pp.stereo_data.rig import Rectifier, read_rig

STATIC = Path(__file__).resolve().parents[2] / "service" / "static"
EXAMPLE = STATIC / "examples" / "raw-320x240"


def make_raw_example() -> ModuleType:
    spec = importlib.util.spec_from_file_location("make_raw_example", STATIC / "make_raw_example.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_shipped_calibration_is_the_rig_the_example_was_made_with_and_the_files_are_small():
    made = make_raw_example()
    rig = read_rig(EXAMPLE / "stereo.yaml")
    assert rig.image_size == (made.WIDTH, made.HEIGHT)
    for name in ("K1", "D1", "K2", "D2"):
        np.testing.assert_allclose(getattr(rig, name.lower()), made.calibration_entries()[name], rtol=1e-12)
    assert rig.baseline == pytest.approx(made.BASELINE_M)
    for name in ("left.png", "right.png"):
        assert cv2.imread(str(EXAMPLE / name)).shape == (made.HEIGHT, made.WIDTH, 3)
    assert sum(path.stat().st_size for path in EXAMPLE.iterdir()) < 300_000


def test_the_raw_example_through_predict_gives_its_true_depth_and_prints_the_rectified_camera(tmp_path, capsys):
    inputs = [str(EXAMPLE / "left.png"), str(EXAMPLE / "right.png"), "--calibration", str(EXAMPLE / "stereo.yaml")]
    outputs = ["-o", str(tmp_path / "d.pfm"), "--depth", str(tmp_path / "z.pfm"), "--depth-mm", str(tmp_path / "z.png")]
    assert main(["predict", *inputs, *outputs, "--frame", "original", "--device", "cpu"]) == 0
    camera, rows, *written = capsys.readouterr().out.splitlines()
    assert camera == describe_camera(Rectifier(read_rig(EXAMPLE / "stereo.yaml")).focal_baseline)
    assert rows.startswith("rows: the right image's lie on the left's (within 0.")  # its calibration rectifies it
    assert camera.startswith("rectified camera: focal length ") and "px, baseline 0.1200 m, principal point (" in camera
    files = (("disparity", "d.pfm"), ("depth", "z.pfm"), ("depth in mm", "z.png"))
    assert written == [f"wrote {what} {tmp_path / name}" for what, name in files]

    depth = read_pfm(tmp_path / "z.pfm")  # metres along the left camera's axis, at the raw left pixels
    truth = cv2.imread(str(EXAMPLE / "depth_mm.png"), cv2.IMREAD_UNCHANGED) / 1000.0
    known = np.isfinite(depth)
    assert known.mean() > 0.9  # the corners the rectified image does not cover have none
    assert (np.abs(depth[known] - truth[known]) <= 0.05 * truth[known]).mean() > 0.8
    millimetres = cv2.imread(str(tmp_path / "z.png"), cv2.IMREAD_UNCHANGED)
    assert millimetres.dtype == np.uint16 and (millimetres[~known] == 0).all()
    np.testing.assert_allclose(millimetres[known], depth[known] * 1000, atol=0.5)

    without_camera = [*inputs[:2], "-o", str(tmp_path / "x.pfm"), "--depth-mm", str(tmp_path / "x.png")]
    assert main(["predict", *without_camera]) == 2
    assert "--depth-mm needs --calibration, or --focal-px and --baseline-m" in capsys.readouterr().err


def test_a_pair_of_another_size_than_the_calibrations_is_refused_before_any_camera_is_printed(tmp_path, capsys):
    for name in ("left.png", "right.png"):  # the example's pair, cropped to 300x240
        cv2.imwrite(str(tmp_path / name), cv2.imread(str(EXAMPLE / name))[:, :300])
    inputs = [str(tmp_path / "left.png"), str(tmp_path / "right.png"), "--calibration", str(EXAMPLE / "stereo.yaml")]
    assert main(["predict", *inputs, "-o", str(tmp_path / "d.pfm"), "--device", "cpu"]) == 2
    printed = capsys.readouterr()
    assert printed.out == ""
    assert "the calibration is for 320x240 images, the left image is 300x240" in printed.err
    assert not (tmp_path / "d.pfm").exists()
