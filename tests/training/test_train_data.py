"""Training batches: the per-step mixture plan and the augmentation of real pairs."""

from collections import Counter
from dataclasses import replace

import numpy as np
import pytest
import torch

import crestereo_pp.training.data
from crestereo_pp.cli.evaluate import PROCEDURAL_SEED
from crestereo_pp.stereo_data.readers import StereoSample
from crestereo_pp.stereo_data.synthetic.draw import SEEDS
from crestereo_pp.training.calibrate import CALIBRATION_SEED
from crestereo_pp.training.config import SYNTHETIC, DataSource, TrainConfig
from crestereo_pp.training.data import HostPartsByStep, TrainingData, augment_real_pair, plan_step


def constant_pair(
    height: int, width: int, disparity: float, known_fraction: float = 1.0, seed: int = 0
) -> StereoSample:
    """A random RGB pair whose ground truth is `disparity` on a random `known_fraction` of pixels."""
    rng = np.random.default_rng(seed)
    image = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    valid = rng.random((height, width)) < known_fraction
    ground_truth = np.where(valid, np.float32(disparity), np.float32(np.inf)).astype(np.float32)
    return StereoSample("pair", image, image.copy(), ground_truth, valid)


def mixture(weights: dict[str, float], batch_size: int = 4) -> TrainConfig:
    return TrainConfig(
        sources=tuple(DataSource(p, w) for p, w in weights.items()),
        batch_size=batch_size,
        crop_height=32,
        crop_width=64,
    )


def test_a_step_plan_depends_only_on_seed_step_and_rank():
    config = mixture({SYNTHETIC: 1.0, "/a": 1.0, "/b": 1.0})
    assert plan_step(config, [10, 20], step=5, rank=0) == plan_step(config, [10, 20], step=5, rank=0)
    assert plan_step(config, [10, 20], step=5, rank=0) != plan_step(config, [10, 20], step=6, rank=0)
    assert plan_step(config, [10, 20], step=5, rank=0) != plan_step(config, [10, 20], step=5, rank=1)


def test_training_never_draws_the_calibration_or_evaluation_scenes():
    """Training's scene seeds stay below 2**31; the calibration's scenes and `eval --procedural`'s
    lie above, apart from each other, within the 32 bits a generator keeps."""
    config = mixture({SYNTHETIC: 1.0})
    drawn = [plan_step(config, [], step, rank).synthetic_seed for step in range(2000) for rank in range(2)]
    assert max(drawn) < 2**31 <= CALIBRATION_SEED
    assert max(drawn) > 2**30  # the whole range below 2**31 is used
    assert CALIBRATION_SEED + 10_000 < PROCEDURAL_SEED and PROCEDURAL_SEED + 10_000 < SEEDS


def test_sources_are_drawn_in_proportion_to_their_weights():
    config = mixture({SYNTHETIC: 3.0, "/a": 1.0})
    drawn: Counter[str] = Counter()
    for step in range(300):
        plan = plan_step(config, [7], step, rank=0)
        assert plan.synthetic_count + len(plan.real) == 4
        drawn[SYNTHETIC] += plan.synthetic_count
        drawn["/a"] += len(plan.real)
        assert all(0 <= draw.index < 7 and draw.source == 0 for draw in plan.real)
    assert drawn[SYNTHETIC] / 1200 == pytest.approx(0.75, abs=0.04)


def test_rescaling_multiplies_the_disparity_by_the_horizontal_scale():
    batch = augment_real_pair(constant_pair(64, 96, 5.0), 32, 64, scale_range=(2.0, 2.0), color_jitter=0.0, seed=0)
    assert batch.left.shape == batch.right.shape == (1, 3, 32, 64) and batch.left.dtype == torch.float32
    assert batch.disparity.shape == batch.valid.shape == (1, 1, 32, 64)
    assert batch.valid.all() and torch.all(batch.disparity == 10.0)


def test_sparse_ground_truth_stays_sparse_and_unblended():
    batch = augment_real_pair(constant_pair(64, 96, 5.0, known_fraction=0.3), 32, 64, (1.3, 1.3), 0.0, seed=1)
    known = batch.valid[0, 0]
    assert 0.2 < known.float().mean() < 0.4
    known_values = batch.disparity[0, 0][known]
    assert torch.allclose(known_values, torch.full_like(known_values, 5.0 * round(96 * 1.3) / 96))
    assert torch.all(batch.disparity[0, 0][~known] == 0.0)  # unknown is 0, never inf, in a batch


def test_a_pair_smaller_than_the_crop_is_enlarged_to_cover_it():
    batch = augment_real_pair(constant_pair(20, 40, 2.0), 32, 64, (0.8, 1.0), 0.0, seed=2)
    assert batch.left.shape == (1, 3, 32, 64)
    assert torch.allclose(batch.disparity, torch.full_like(batch.disparity, 2.0 * 64 / 40))


def test_color_jitter_changes_the_two_views_independently_within_bounds():
    sample = constant_pair(32, 64, 1.0)
    plain = augment_real_pair(sample, 32, 64, (1.0, 1.0), 0.0, seed=3)
    jittered = augment_real_pair(sample, 32, 64, (1.0, 1.0), 0.2, seed=3)
    assert torch.equal(plain.left, torch.from_numpy(sample.left.astype(np.float32)).permute(2, 0, 1)[None])
    ratio_left = jittered.left.sum(dim=(2, 3)) / plain.left.sum(dim=(2, 3))
    ratio_right = jittered.right.sum(dim=(2, 3)) / plain.right.sum(dim=(2, 3))
    assert not torch.allclose(ratio_left, ratio_right)
    assert ((ratio_left > 0.75) & (ratio_left < 1.2)).all()  # gains in [0.8, 1.2], clipping at 255 only lowers


def test_host_parts_without_a_generator_hold_only_the_real_part_of_each_batch():
    config = mixture({SYNTHETIC: 1.0, "/a": 1.0}, batch_size=4)
    pairs = HostPartsByStep(config, [[constant_pair(64, 96, 3.0)]], rank=0)
    for step in range(5):
        plan = plan_step(config, [1], step, rank=0)
        part = pairs[step]
        assert (part is None) if not plan.real else part.left.shape[0] == len(plan.real)


def test_training_data_mixes_sources_into_full_batches(monkeypatch):
    monkeypatch.setattr(
        crestereo_pp.training.data, "open_dataset", lambda path: [constant_pair(64, 96, 4.0, known_fraction=0.5)]
    )
    config = TrainConfig(
        sources=(DataSource("/fake", 1.0),), batch_size=2, crop_height=32, crop_width=64, max_steps=3, num_workers=0
    )
    batches = list(TrainingData(config, rank=0, device=torch.device("cpu")).batches(start_step=1))
    assert len(batches) == 2  # steps 1 and 2
    for batch in batches:
        assert batch.left.shape == (2, 3, 32, 64) and batch.valid.dtype == torch.bool
        assert torch.isfinite(batch.disparity).all()


def test_procedural_scenes_made_in_loader_workers_equal_those_made_inline():
    config = TrainConfig(batch_size=2, crop_height=32, crop_width=64, max_steps=3, max_disparity=16.0)
    inline = list(TrainingData(replace(config, num_workers=0), rank=0, device=torch.device("cpu")).batches(1))
    workers = list(TrainingData(replace(config, num_workers=1), rank=0, device=torch.device("cpu")).batches(1))
    assert len(inline) == len(workers) == 2
    for a, b in zip(inline, workers, strict=True):
        assert torch.equal(a.left, b.left) and torch.equal(a.disparity, b.disparity)
