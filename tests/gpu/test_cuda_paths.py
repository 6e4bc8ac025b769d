"""Every path that takes a device, end to end on CUDA: predictor, training (bf16, fused AdamW) with
its checkpoint exported and loaded on the CPU, calibration and evaluation. Skipped without CUDA;
bench/gpu_check runs them on a GPU machine."""

import warnings

import numpy as np
import pytest
import torch

from crestereo_pp.evaluation.evaluate import evaluate
from crestereo_pp.inference import load_model
from crestereo_pp.model.weights import read_weights
from crestereo_pp.stereo_data.readers import StereoSample
from crestereo_pp.training.calibrate import calibrate
from crestereo_pp.training.config import TrainConfig
from crestereo_pp.training.export import export_weights
from crestereo_pp.training.trainer import train

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
ITERS = (1, 1, 2)


@pytest.fixture(scope="module")
def lite():
    return load_model("lite", device="cuda")


def shifted_sample(name: str, disparity: int, seed: int, height: int = 96, width: int = 160) -> StereoSample:
    """A random texture and the same texture shifted by `disparity` px (unknown where it leaves the view)."""
    rng = np.random.default_rng(seed)
    texture = rng.integers(0, 256, (height, width + disparity, 3), dtype=np.uint8)
    truth = np.full((height, width), float(disparity), np.float32)
    truth[:, :disparity] = np.inf
    return StereoSample(name, texture[:, :width].copy(), texture[:, disparity:].copy(), truth, np.isfinite(truth), None)


def test_predict_keeps_tensors_on_cuda_and_gives_arrays_for_arrays(lite):
    sample = shifted_sample("pair", 8, seed=0)
    from_arrays = lite.predict(sample.left, sample.right, iters=ITERS)
    assert isinstance(from_arrays.disparity, np.ndarray) and from_arrays.disparity.shape == sample.disparity.shape
    left = torch.from_numpy(sample.left).permute(2, 0, 1)[None].cuda()
    right = torch.from_numpy(sample.right).permute(2, 0, 1)[None].cuda()
    from_tensors = lite.predict(left, right, iters=ITERS)
    assert from_tensors.disparity.device.type == from_tensors.uncertainty.device.type == "cuda"
    np.testing.assert_allclose(from_tensors.disparity[0].cpu().numpy(), from_arrays.disparity, atol=1e-3)


def test_training_on_cuda_saves_a_checkpoint_that_exports_and_loads_on_the_cpu(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.backends.cudnn, "benchmark", torch.backends.cudnn.benchmark)  # the trainer sets it
    config = TrainConfig(
        crop_height=64,
        crop_width=96,
        batch_size=2,
        max_steps=3,
        train_iters=(1, 1, 1),
        warmup_fraction=0.0,
        log_every=1,
        num_workers=0,
        device="cuda",
        out_dir=str(tmp_path / "run"),
    )
    result = train(config, progress=False)
    assert result.step == 3 and next(result.network.parameters()).is_cuda
    checkpoint = read_weights(result.checkpoint)
    assert all(t.device.type == "cpu" for t in checkpoint["model"].values())
    assert checkpoint["training"]["runs"][-1]["device"] == torch.cuda.get_device_name()
    exported = tmp_path / "lite.pt"
    export_weights(result.checkpoint, exported)
    on_cpu = load_model("lite", exported, device="cpu")
    left = np.zeros((64, 96, 3), np.uint8)
    assert np.isfinite(on_cpu.predict(left, left, iters=ITERS).disparity).all()


def test_calibration_fits_on_cuda(lite):
    calibration = calibrate(lite, scenes=2, batch_size=2)
    assert len(calibration.knots) >= 2 and 0.0 <= calibration.probabilities[0] <= 1.0


def test_evaluation_runs_on_cuda(lite):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        report = evaluate(
            [shifted_sample(f"pair{i}", 4 + 4 * i, i) for i in range(2)],
            lite,
            dataset_name="scenes",
            iters=ITERS,
            progress=False,
        )
    assert len(report.pairs) == 2 and np.isfinite(report.mean("lite").metrics.epe)
