"""ONNX export (`crestereo-pp export --onnx`): ONNX Runtime gives what `predict` gives."""

from __future__ import annotations

import numpy as np
import pytest

from crestereo_pp.cli.main import main
from crestereo_pp.inference import NETWORK_ONLY, load_model
from crestereo_pp.model.weights import WEIGHTS_DIR
from crestereo_pp.stereo_data.synthetic import SceneConfig, SceneGenerator

ort = pytest.importorskip("onnxruntime", reason="onnxruntime is a test dependency (pip install -e '.[test]')")


def test_exported_model_in_onnx_runtime_matches_predict_within_a_thousandth_of_a_pixel(tmp_path, capsys):
    """The bundled lite weights (calibrated), fewer iterations to keep the export short."""
    weights = WEIGHTS_DIR / "lite.pt"
    onnx_file = tmp_path / "lite.onnx"
    # 50x90 is not a multiple of 32: the graph pads it as predict does
    command = [
        "export",
        str(weights),
        "-o",
        str(onnx_file),
        "--onnx",
        "--height",
        "50",
        "--width",
        "90",
        "--iters",
        "1",
        "1",
        "2",
    ]
    assert main(command) == 0
    assert "input 1x3x50x90" in capsys.readouterr().out

    left, right = procedural_pair()
    predictor = load_model("lite", weights)
    assert predictor.calibration is not None
    # the graph is one pass of the network (no blend with SGBM)
    expected = predictor.predict(left, right, iters=(1, 1, 2), two_pass=False, **NETWORK_ONLY)
    session = ort.InferenceSession(str(onnx_file), providers=["CPUExecutionProvider"])
    as_input = lambda image: np.ascontiguousarray(image.transpose(2, 0, 1)[None], dtype=np.float32)  # noqa: E731
    disparity, uncertainty = session.run(None, {"left": as_input(left), "right": as_input(right)})
    assert disparity.shape == uncertainty.shape == (1, 1, 50, 90)
    assert np.abs(disparity[0, 0] - expected.disparity).max() < 1e-3
    assert np.abs(uncertainty[0, 0] - expected.uncertainty).max() < 1e-4


def procedural_pair() -> tuple[np.ndarray, np.ndarray]:
    """A 50x90 procedural scene (stereo_data.synthetic) as HxWx3 float arrays in [0, 255]."""
    batch = SceneGenerator(SceneConfig(height=50, width=90, max_disparity=20.0)).generate(batch_size=1, seed=5)
    return batch.left[0].permute(1, 2, 0).numpy(), batch.right[0].permute(1, 2, 0).numpy()


def test_onnx_export_without_a_size_is_a_clear_usage_error(tmp_path, capsys):
    assert main(["export", str(tmp_path / "any.pt"), "-o", str(tmp_path / "m.onnx"), "--onnx"]) == 2
    assert "crestereo-pp export: error: --onnx needs --height and --width" in capsys.readouterr().err
