"""Training runs on the CPU at tiny sizes: outputs, exact resume, time budget, init weights, export."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

import crestereo_pp.training.data
import crestereo_pp.training.trainer
from crestereo_pp.cli.main import main
from crestereo_pp.inference import load_model
from crestereo_pp.model.network import CREStereoPP
from crestereo_pp.model.weights import read_weights
from crestereo_pp.stereo_data.readers import StereoSample
from crestereo_pp.training.config import DataSource, TrainConfig
from crestereo_pp.training.records import read_csv
from crestereo_pp.training.trainer import takes_two_passes, train
from training_helpers import tiny


def textured_pair(seed: int, disparity: float = 3.0) -> StereoSample:
    """A 64x96 random-texture pair shifted by `disparity` px (left x = right x - disparity)."""
    rng = np.random.default_rng(seed)
    texture = rng.integers(0, 256, (64, 96 + int(disparity), 3), dtype=np.uint8)
    truth = np.full((64, 96), disparity, np.float32)
    return StereoSample(
        f"pair{seed}", texture[:, :96].copy(), texture[:, int(disparity) :].copy(), truth, np.ones((64, 96), bool)
    )


@pytest.fixture
def real_pairs(monkeypatch) -> DataSource:
    """A training source of three in-memory real pairs (open_dataset is replaced for the test)."""
    pairs = [textured_pair(seed, 2.0 + seed) for seed in range(3)]
    monkeypatch.setattr(crestereo_pp.training.data, "open_dataset", lambda path: pairs)
    monkeypatch.setattr(crestereo_pp.training.trainer, "open_dataset", lambda path: pairs)
    return DataSource("/in-memory", 1.0)


def losses(out_dir: Path) -> list[float]:
    return [float(row["loss"]) for row in read_csv(out_dir / "log.csv")]


def test_train_command_runs_steps_on_procedural_scenes_and_leaves_checkpoint_log_and_curve(tmp_path):
    out = tmp_path / "run"
    status = main(
        [
            "train",
            "--crop-height",
            "64",
            "--crop-width",
            "96",
            "--batch-size",
            "1",
            "--max-steps",
            "2",
            "--log-every",
            "1",
            "--device",
            "cpu",
            "--out-dir",
            str(out),
            "--no-progress",
        ]
    )
    assert status == 0
    checkpoint = read_weights(out / "checkpoint.pt")
    assert {
        "model",
        "config",
        "model_name",
        "train_config",
        "optimizer",
        "scheduler",
        "step",
        "rng",
        "training",
    } <= set(checkpoint)
    assert checkpoint["step"] == 2 and checkpoint["model_name"] == "lite"
    assert TrainConfig.from_dict(checkpoint["train_config"]).sources == (DataSource("synthetic"),)
    rows = read_csv(out / "log.csv")
    assert [int(r["step"]) for r in rows] == [1, 2] and all(np.isfinite(float(r["loss"])) for r in rows)
    assert float(rows[-1]["pairs_per_second"]) > 0
    assert (out / "loss_curve.png").stat().st_size > 0
    # a checkpoint is a weights file (docs/CONTRACTS.md)
    with pytest.warns(RuntimeWarning, match="are untrained"):  # two steps
        loaded = load_model("lite", weights=out / "checkpoint.pt").network.state_dict()
    assert all(torch.equal(loaded[name], tensor) for name, tensor in checkpoint["model"].items())


def test_a_resumed_run_repeats_the_uninterrupted_run_exactly(tmp_path, real_pairs):
    whole = tiny(tmp_path / "whole", sources=(real_pairs,), max_steps=4, schedule_steps=4)
    train(whole, progress=False)
    # interrupted after 2 steps (same schedule), with a loader worker this time, then resumed in-process
    first = replace(whole, out_dir=str(tmp_path / "split"), max_steps=2, num_workers=1)
    train(first, progress=False)
    resumed = replace(first, max_steps=4, num_workers=0)
    result = train(resumed, resume=tmp_path / "split" / "checkpoint.pt", progress=False)

    assert result.step == 4
    assert losses(tmp_path / "split") == losses(tmp_path / "whole")  # bit-exact, all four steps
    a = read_weights(tmp_path / "whole" / "checkpoint.pt")["model"]
    b = read_weights(tmp_path / "split" / "checkpoint.pt")["model"]
    assert all(torch.equal(a[name], b[name]) for name in a)
    history = read_weights(tmp_path / "split" / "checkpoint.pt")["training"]
    assert [run["origin"] for run in history["runs"]] == ["scratch", "resume"] and history["total_steps"] == 4


def test_a_resumed_run_with_a_larger_batch_counts_pairs_on_from_the_checkpoints_total(tmp_path, real_pairs):
    train(tiny(tmp_path, sources=(real_pairs,), max_steps=2), progress=False)  # 2 steps of 1 pair
    resumed = tiny(tmp_path, sources=(real_pairs,), max_steps=4, batch_size=3)
    train(resumed, resume=tmp_path / "checkpoint.pt", progress=False)  # 2 steps of 3 pairs

    rows = read_csv(tmp_path / "log.csv")
    assert [int(r["step"]) for r in rows] == [1, 2, 3, 4]
    assert [int(r["pairs_seen"]) for r in rows] == [1, 2, 5, 8]
    history = read_weights(tmp_path / "checkpoint.pt")["training"]
    assert [run["pairs"] for run in history["runs"]] == [2, 6] and history["total_pairs"] == 8


def test_two_pass_steps_refine_the_networks_own_half_resolution_disparity_and_resume_exactly(
    tmp_path, real_pairs, monkeypatch
):
    calls = []
    forward = CREStereoPP.forward

    def recording(self, left, right, iters=None, init_disparity=None):
        calls.append((tuple(left.shape[-2:]), init_disparity is not None, torch.is_grad_enabled()))
        return forward(self, left, right, iters, init_disparity)

    monkeypatch.setattr(CREStereoPP, "forward", recording)
    every = tiny(tmp_path / "every", sources=(real_pairs,), crop_width=128, max_steps=1, two_pass_fraction=1.0)
    train(every, progress=False)
    # the half-resolution pass without a gradient, then the trained refinement from it
    assert calls == [((32, 64), False, False), ((64, 128), True, True)]
    assert np.isfinite(losses(tmp_path / "every")).all()

    half = replace(every, out_dir=str(tmp_path / "whole"), two_pass_fraction=0.5, max_steps=4, schedule_steps=4)
    drawn = [takes_two_passes(half, step) for step in range(4)]
    assert 0 < sum(drawn) < 4  # both kinds of step, for the resume below
    calls.clear()
    train(half, progress=False)
    assert sum(init for _, init, _ in calls) == sum(drawn)
    train(replace(half, out_dir=str(tmp_path / "split"), max_steps=2), progress=False)
    train(replace(half, out_dir=str(tmp_path / "split")), resume=tmp_path / "split" / "checkpoint.pt", progress=False)
    assert losses(tmp_path / "split") == losses(tmp_path / "whole")


def test_two_pass_steps_are_drawn_with_the_configured_fraction():
    config = TrainConfig(two_pass_fraction=0.3, crop_height=128, crop_width=256)
    share = np.mean([takes_two_passes(config, step) for step in range(2000)])
    assert 0.27 < share < 0.33
    assert not any(takes_two_passes(replace(config, two_pass_fraction=0.0), step) for step in range(200))


def test_the_time_budget_stops_after_the_current_step_and_saves_it(tmp_path, real_pairs):
    result = train(tiny(tmp_path, sources=(real_pairs,), max_steps=50, max_minutes=0.0), progress=False)
    assert result.out_of_time and result.step == 1
    assert read_weights(result.checkpoint)["step"] == 1


class StepClock:
    """A stand-in for the trainer's clock on which every training step takes `seconds`."""

    def __init__(self, seconds: float) -> None:
        self.now, self.seconds = 0.0, seconds

    def monotonic(self) -> float:
        return self.now


def test_a_flat_decay_run_slower_than_planned_brings_its_decay_forward_to_end_decayed_in_its_time(
    tmp_path, real_pairs, monkeypatch
):
    clock = StepClock(10.0)
    monkeypatch.setattr(crestereo_pp.training.trainer, "time", clock)
    real_step = crestereo_pp.training.trainer.Trainer.train_step

    def timed_step(self, *args, **kwargs):
        clock.now += clock.seconds
        return real_step(self, *args, **kwargs)

    monkeypatch.setattr(crestereo_pp.training.trainer.Trainer, "train_step", timed_step)
    # planned: 20 steps, the last 8 decaying; the budget (155 s at 10 s a step) holds 15
    config = tiny(tmp_path, sources=(real_pairs,), max_steps=20, schedule="flat-decay", decay_steps=8, lr=1e-4)
    config = replace(config, max_minutes=155 / 60)
    result = train(config, progress=False)

    assert result.step == 15 and not result.out_of_time
    lrs = [float(row["lr"]) for row in read_csv(tmp_path / "log.csv")]
    # the peak until the decay, which keeps its share of the run (0.4: 6 of 15 steps) and begins at step 9
    assert lrs[:10] == pytest.approx([1e-4] * 10)
    assert lrs[9:] == pytest.approx([1e-4 * (15 - step) / 6 for step in range(9, 15)])
    assert read_weights(tmp_path / "stable.pt")["step"] == 9
    assert read_weights(result.checkpoint)["train_config"]["max_steps"] == 15

    # where the steps fit, nothing moves
    clock.seconds, clock.now = 5.0, 0.0
    result = train(replace(config, out_dir=str(tmp_path / "in-time")), progress=False)
    assert result.step == 20 and read_weights(tmp_path / "in-time" / "stable.pt")["step"] == 12


def test_a_flat_decay_run_whose_first_steps_ran_slow_takes_back_the_steps_that_fit_once_it_speeds_up(
    tmp_path, real_pairs, monkeypatch
):
    clock = StepClock(5.0)
    monkeypatch.setattr(crestereo_pp.training.trainer, "time", clock)
    real_step = crestereo_pp.training.trainer.Trainer.train_step
    steps_taken = []

    def timed_step(self, *args, **kwargs):
        steps_taken.append(1)
        clock.now += 20.0 if len(steps_taken) in (2, 3) else 5.0  # steps 2 and 3 slow, the rest 5 s
        return real_step(self, *args, **kwargs)

    monkeypatch.setattr(crestereo_pp.training.trainer.Trainer, "train_step", timed_step)
    # planned: 20 steps, the last 8 decaying, in 155 s; after step 2 the rate so far (20 s a step) fits
    # only 8 steps, but as the 5 s steps come in the end moves out again, up to step 19
    config = tiny(tmp_path, sources=(real_pairs,), max_steps=20, schedule="flat-decay", decay_steps=8, lr=1e-4)
    result = train(replace(config, max_minutes=155 / 60), progress=False)

    assert result.step == 19 and not result.out_of_time and clock.now <= 155
    lrs = [float(row["lr"]) for row in read_csv(tmp_path / "log.csv")]
    assert lrs[:11] == pytest.approx([1e-4] * 11)  # at the peak until the decay that fits: 8 of 19 steps
    assert lrs[11:] == pytest.approx([1e-4 * (19 - step) / 8 for step in range(11, 19)])
    assert read_weights(tmp_path / "stable.pt")["step"] == 11


def test_resume_options_override_the_checkpoint_config(tmp_path, real_pairs):
    train(tiny(tmp_path, sources=(real_pairs,), max_steps=1, schedule="constant"), progress=False)
    checkpoint = tmp_path / "checkpoint.pt"
    status = main(["train", "--resume", str(checkpoint), "--max-steps", "2", "--lr", "1e-5", "--no-progress"])
    assert status == 0
    rows = read_csv(tmp_path / "log.csv")
    assert [float(r["lr"]) for r in rows] == [4e-4, 1e-5]


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_a_checkpoint_trained_on_a_gpu_resumes_on_a_cpu_only_with_another_device_and_says_so(
    tmp_path, real_pairs, capsys
):
    train(tiny(tmp_path, sources=(real_pairs,), max_steps=1), progress=False)
    checkpoint = tmp_path / "checkpoint.pt"
    saved = read_weights(checkpoint)
    saved["train_config"]["device"] = "cuda"  # as the GPU check's training stage records it
    torch.save(saved, checkpoint)

    assert main(["train", "--resume", str(checkpoint), "--max-steps", "2", "--no-progress"]) == 2
    error = capsys.readouterr().err
    assert "CUDA is not available" in error and "'cpu'" in error and "Traceback" not in error
    assert main(["train", "--resume", str(checkpoint), "--max-steps", "2", "--device", "cpu", "--no-progress"]) == 0
    assert read_weights(checkpoint)["step"] == 2


def test_init_weights_start_a_fresh_run_that_carries_the_history(tmp_path, real_pairs):
    train(tiny(tmp_path / "a", sources=(real_pairs,), max_steps=1), progress=False)
    weights = tmp_path / "a.pt"
    assert main(["export", str(tmp_path / "a" / "checkpoint.pt"), "-o", str(weights)]) == 0
    # lr 0: the weights cannot move, so they must come out as they went in
    result = train(
        tiny(tmp_path / "b", sources=(real_pairs,), max_steps=2, lr=0.0), init_weights=weights, progress=False
    )

    assert result.step == 2
    start = read_weights(weights)["model"]
    assert all(torch.equal(start[name], tensor) for name, tensor in result.network.state_dict().items())
    history = read_weights(result.checkpoint)["training"]
    assert [run["origin"] for run in history["runs"]] == ["scratch", "init-weights"]
    assert history["total_steps"] == 3 and history["total_pairs"] == 3


def test_weights_of_another_model_are_refused(tmp_path, real_pairs):
    train(tiny(tmp_path / "a", sources=(real_pairs,), max_steps=1), progress=False)
    with pytest.raises(ValueError, match="holds 'lite' weights, not 'full'"):
        train(tiny(tmp_path / "b", model="full", sources=(real_pairs,)), init_weights=tmp_path / "a" / "checkpoint.pt")


def test_validation_at_checkpoints_is_logged(tmp_path, real_pairs):
    train(tiny(tmp_path, sources=(real_pairs,), max_steps=2, checkpoint_every=1, val_data="/in-memory"), progress=False)
    rows = read_csv(tmp_path / "validation.csv")
    assert [int(r["step"]) for r in rows] == [1, 2]
    assert all(float(r["epe"]) >= 0 and 0 <= float(r["bad2"]) <= 100 for r in rows)
    assert (tmp_path / "validation_curve.png").is_file()
    assert read_weights(tmp_path / "checkpoint.pt")["training"]["runs"][-1]["validation"]["bad2"] == float(
        rows[-1]["bad2"]
    )


def test_validation_computes_each_pair_in_one_pass_so_the_learning_curve_measures_the_network(
    tmp_path, real_pairs, monkeypatch
):
    options = []
    evaluate = crestereo_pp.training.trainer.evaluate

    def recording(*args, **kwargs):
        options.append(kwargs["options"])
        return evaluate(*args, **kwargs)

    monkeypatch.setattr(crestereo_pp.training.trainer, "evaluate", recording)
    train(tiny(tmp_path, sources=(real_pairs,), max_steps=1, checkpoint_every=1, val_data="/in-memory"), progress=False)
    assert [o.two_pass for o in options] == [False]


def test_fp16_export_halves_the_file_and_predicts_like_fp32(tmp_path, real_pairs):
    train(tiny(tmp_path, sources=(real_pairs,), max_steps=1), progress=False)
    full, half = tmp_path / "fp32.pt", tmp_path / "fp16.pt"
    assert main(["export", str(tmp_path / "checkpoint.pt"), "-o", str(full)]) == 0
    assert main(["export", str(tmp_path / "checkpoint.pt"), "-o", str(half), "--fp16"]) == 0

    exported = read_weights(half)
    assert {"model", "config", "training"} <= set(exported) and "optimizer" not in exported
    assert half.stat().st_size < 0.6 * full.stat().st_size
    pair = textured_pair(7)
    with pytest.warns(RuntimeWarning, match="are untrained"):
        a = load_model("lite", weights=full).predict(pair.left, pair.right).disparity
    with pytest.warns(RuntimeWarning, match="are untrained"):
        b = load_model("lite", weights=half).predict(pair.left, pair.right).disparity
    assert np.abs(a - b).max() < 0.05 * max(1.0, np.abs(a).max())


def test_with_ema_the_checkpoint_serves_the_average_of_the_trained_weights(tmp_path, real_pairs):
    # the average starts as the weights trained from (seed 0's init), then moves by 1 - decay each step
    start = train(tiny(tmp_path / "start", sources=(real_pairs,), lr=0.0, max_steps=1), progress=False)
    one = train(tiny(tmp_path / "one", sources=(real_pairs,), max_steps=1), progress=False)
    two = train(tiny(tmp_path / "two", sources=(real_pairs,), max_steps=2, ema_decay=0.75), progress=False)

    checkpoint = read_weights(two.checkpoint)
    w0, w1 = start.network.state_dict(), one.network.state_dict()
    w2 = checkpoint["train_model"]
    for name, served in checkpoint["model"].items():
        expected = 0.75 * (0.75 * w0[name] + 0.25 * w1[name]) + 0.25 * w2[name]
        assert torch.allclose(served, expected, atol=1e-6), name
    assert any(not torch.equal(checkpoint["model"][n], w2[n]) for n in w2)
    # load_model serves the average
    with pytest.warns(RuntimeWarning, match="are untrained"):
        loaded = load_model("lite", weights=two.checkpoint).network.state_dict()
    assert all(torch.equal(loaded[name], tensor) for name, tensor in checkpoint["model"].items())


def test_a_resumed_ema_run_repeats_the_uninterrupted_run_exactly(tmp_path, real_pairs):
    whole = tiny(tmp_path / "whole", sources=(real_pairs,), max_steps=4, schedule_steps=4, ema_decay=0.5)
    train(whole, progress=False)
    first = replace(whole, out_dir=str(tmp_path / "split"), max_steps=2)
    train(first, progress=False)
    train(replace(first, max_steps=4), resume=tmp_path / "split" / "checkpoint.pt", progress=False)

    a = read_weights(tmp_path / "whole" / "checkpoint.pt")
    b = read_weights(tmp_path / "split" / "checkpoint.pt")
    for key in ("model", "train_model"):
        assert all(torch.equal(a[key][name], b[key][name]) for name in a[key]), key
    assert losses(tmp_path / "split") == losses(tmp_path / "whole")


def test_turning_ema_on_at_a_resume_starts_the_average_from_the_resumed_weights(tmp_path, real_pairs):
    train(tiny(tmp_path, sources=(real_pairs,), max_steps=1), progress=False)
    before = read_weights(tmp_path / "checkpoint.pt")["model"]
    resumed = tiny(tmp_path, sources=(real_pairs,), max_steps=2, lr=0.0, ema_decay=0.9)
    train(resumed, resume=tmp_path / "checkpoint.pt", progress=False)

    after = read_weights(tmp_path / "checkpoint.pt")  # lr 0: neither the weights nor their average move
    assert all(
        torch.equal(after["model"][n], before[n]) and torch.equal(after["train_model"][n], before[n]) for n in before
    )


def test_with_ema_validation_logs_the_served_average_and_the_raw_weights(tmp_path, real_pairs):
    config = tiny(
        tmp_path, sources=(real_pairs,), max_steps=2, checkpoint_every=1, val_data="/in-memory", ema_decay=0.9
    )
    train(config, progress=False)
    rows = read_csv(tmp_path / "validation.csv")
    assert [int(r["step"]) for r in rows] == [1, 2]
    assert all(float(r["raw_epe"]) >= 0 and 0 <= float(r["raw_bad2"]) <= 100 for r in rows)
    assert any(r["raw_epe"] != r["epe"] for r in rows)  # two different networks were validated


def test_a_flat_decay_run_keeps_its_stable_branch_where_the_decay_begins_and_a_resume_goes_on_at_the_peak_lr(
    tmp_path, real_pairs
):
    decayed = tiny(
        tmp_path / "decayed", sources=(real_pairs,), max_steps=4, schedule="flat-decay", decay_steps=2, lr=1e-4
    )
    train(decayed, progress=False)
    # the same run stopped where its decay begins: the stable branch, saved beside the decayed end
    flat = replace(decayed, out_dir=str(tmp_path / "flat"), max_steps=2, schedule_steps=4)
    train(flat, progress=False)
    stable = read_weights(tmp_path / "decayed" / "stable.pt")
    reference = read_weights(tmp_path / "flat" / "checkpoint.pt")
    assert stable["step"] == 2 and stable["scheduler"]["last_epoch"] == 2
    assert all(torch.equal(stable["model"][name], reference["model"][name]) for name in reference["model"])
    assert stable["training"]["runs"][-1]["last_step"] == 2

    # the next run resumes the stable branch with a later horizon: its first steps are at the peak lr
    onward = replace(decayed, out_dir=str(tmp_path / "onward"), max_steps=6, schedule_steps=6)
    train(onward, resume=tmp_path / "decayed" / "stable.pt", progress=False)
    assert [float(row["lr"]) for row in read_csv(tmp_path / "onward" / "log.csv")][:2] == [1e-4, 1e-4]
    assert not (tmp_path / "flat" / "stable.pt").exists()  # a run that ends where its decay begins keeps none
