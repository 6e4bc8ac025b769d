"""Every path keeps its tensors on the device and copies to the host once, at the edge: proven on
the CPU with a predictor and a trainer on the data-less "meta" device (fake_accelerator)."""

import numpy as np
import pytest
import torch

from crestereo_pp.evaluation.evaluate import evaluate
from crestereo_pp.inference import InferenceOptions, StereoPredictor
from crestereo_pp.inference.cuda_graphs import GraphedForward
from crestereo_pp.model import CREStereoPP, ModelConfig
from crestereo_pp.stereo_data.readers import StereoSample
from crestereo_pp.training.config import TrainConfig
from crestereo_pp.training.data import TrainingBatch
from crestereo_pp.training.distributed import DistributedContext
from crestereo_pp.training.trainer import Trainer
from fake_accelerator import DEVICE, DeviceTransfers, replay_eagerly

ITERS = (1, 1, 2)


@pytest.fixture(scope="module")
def network():
    return CREStereoPP(ModelConfig.preset("lite"))


@pytest.fixture
def predictor(network):
    return StereoPredictor(network, "lite", None, DEVICE)


def pair(height, width, seed=0):
    rng = np.random.default_rng(seed)
    return tuple(rng.integers(0, 256, (height, width, 3), dtype=np.uint8) for _ in range(2))


@pytest.mark.parametrize(
    "options", [{}, {"two_pass": True}, {"scale": 0.5}, {"init_disparity": np.ones((40, 60), np.float32)}]
)
def test_predict_of_arrays_uploads_the_inputs_and_downloads_both_maps_in_one_copy(predictor, options):
    left, right = pair(40, 60)
    with DeviceTransfers() as transfers:
        prediction = predictor.predict(left, right, iters=ITERS, **options)
    assert isinstance(prediction.disparity, np.ndarray) and prediction.disparity.shape == (40, 60)
    assert prediction.uncertainty.shape == (40, 60)
    assert transfers.downloads == 1 and transfers.download_shapes == [(2, 40, 60)]
    assert transfers.uploads == 2 + ("init_disparity" in options) and transfers.scalar_reads == 0


@pytest.mark.parametrize(
    ("blend_sgbm", "refine_edges", "transfers_made"),
    [(False, False, (0, 0, 0)), (True, True, (1, 6, 0)), (False, True, (1, 4, 0))],
)
def test_predict_of_device_tensors_leaves_the_maps_on_the_device_and_the_refinement_copies_once(
    predictor, blend_sgbm, refine_edges, transfers_made
):
    """Without the host refinement nothing crosses; with it each pair's answer and the images it
    reads come to the host once (the answer, the left image and, for the blend, the right one, for
    each of 2 pairs) and the refined answers go back in one copy."""
    left = torch.rand(2, 3, 40, 60, device=DEVICE) * 255
    with DeviceTransfers() as transfers:
        prediction = predictor.predict(left, left, iters=ITERS, blend_sgbm=blend_sgbm, refine_edges=refine_edges)
    assert prediction.disparity.device == prediction.uncertainty.device == DEVICE
    assert prediction.disparity.shape == (2, 40, 60)
    assert (transfers.uploads, transfers.downloads, transfers.scalar_reads) == transfers_made


@pytest.mark.parametrize("graphs", [False, True], ids=["eager", "graphed"])
def test_predict_batch_downloads_the_whole_batch_in_one_copy(predictor, graphs):
    if graphs:
        predictor.graphs = GraphedForward(predictor.forward, capture=replay_eagerly, capture_after=1)
    pairs = [pair(40, 60, 1), pair(33, 64, 2), pair(40, 50, 3)]
    for _ in range(2):  # with graphs: capture, then replay
        with DeviceTransfers() as transfers:
            results = predictor.predict_batch([p[0] for p in pairs], [p[1] for p in pairs], iters=ITERS)
        assert [r.disparity.shape for r in results] == [(40, 60), (33, 64), (40, 50)]
        assert all(isinstance(r.uncertainty, np.ndarray) for r in results)
        assert transfers.downloads == 1 and transfers.download_shapes == [(2, 3, 64, 64)]
        assert transfers.uploads == 6 and transfers.scalar_reads == 0
    if graphs:
        assert predictor.graphs.replays == 2


def test_evaluation_copies_each_prediction_to_the_host_once(predictor):
    samples = []
    for index in range(2):
        left, right = pair(40, 60, index)
        disparity = np.full((40, 60), 3.0, np.float32)
        samples.append(StereoSample(f"pair{index}", left, right, disparity, np.ones((40, 60), bool), None))
    with DeviceTransfers() as transfers:
        options = InferenceOptions(iters=ITERS)
        report = evaluate(samples, predictor, dataset_name="meta", options=options, progress=False)
    assert len(report.pairs) == 2
    assert transfers.downloads == 2  # one per pair (torch compiles nothing, so nothing is warmed up)
    assert transfers.scalar_reads == 0


@pytest.mark.parametrize("matching_weight", [0.0, 0.1])
def test_a_training_step_keeps_every_tensor_on_the_device(tmp_path, matching_weight):
    config = TrainConfig(
        crop_height=64,
        crop_width=96,
        batch_size=1,
        train_iters=ITERS,
        matching_weight=matching_weight,
        device="meta",
        out_dir=str(tmp_path),
        num_workers=0,
    )
    trainer = Trainer(config, DistributedContext(rank=0, world_size=1, local_rank=0), DEVICE, None, None)
    batch = TrainingBatch(
        torch.rand(1, 3, 64, 96, device=DEVICE) * 255,
        torch.rand(1, 3, 64, 96, device=DEVICE) * 255,
        torch.rand(1, 1, 64, 96, device=DEVICE) * 20,
        torch.ones(1, 1, 64, 96, dtype=torch.bool, device=DEVICE),
    )
    with DeviceTransfers() as transfers:
        loss_and_epe = trainer.train_step(batch)
    assert loss_and_epe.device == DEVICE and loss_and_epe.shape == (2,)
    assert (transfers.uploads, transfers.downloads, transfers.scalar_reads) == (0, 0, 0)
