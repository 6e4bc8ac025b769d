"""The prepared GPU check (bench/gpu_check.py) runs every stage end to end in its CPU smoke mode:
what a GPU machine will run, at tiny sizes, so that its first run there is not its first run."""

import argparse
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

from model.weights import read_weights

REPO = Path(__file__).resolve().parents[2]
STAGES = ("environment", "tests", "bench", "service", "train")


@pytest.fixture
def gpu_check(monkeypatch):
    spec = importlib.util.spec_from_file_location("gpu_check", REPO / "bench/gpu_check.py")
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "gpu_check", module)  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def test_without_fastapi_the_service_stage_is_skipped_saying_so(gpu_check, monkeypatch):
    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        gpu_check.importlib.util, "find_spec", lambda name: None if name == "fastapi" else real_find_spec(name)
    )
    result = gpu_check.service_stage(gpu_check.GPU, 0.0, None, None)
    assert (result.status, result.detail) == ("skipped", "skipped: fastapi not installed (carry wheels: --wheels)")


def test_the_cpu_smoke_run_passes_every_stage_and_keeps_to_the_output_limits(tmp_path):
    out = tmp_path / "out"
    completed = subprocess.run(
        [sys.executable, "bench/gpu_check.py", "--cpu-smoke", "--out", str(out)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    summary = (out / "summary.md").read_text()
    assert completed.returncode == 0, summary + completed.stderr[-3000:]
    assert summary.startswith("# GPU check: CPU smoke run (no GPU: no number here is a GPU number)")
    for stage in STAGES:
        assert f"| {stage} | passed |" in summary, summary

    files = {path.name: path.stat().st_size for path in out.iterdir()}
    assert {"gpu_check.log", "summary.md", "bench.json", "checkpoint.pt", "log.csv", "loss_curve.png"} <= set(files)
    assert (
        len(files) <= 8
        and all(size < 16 * 2**20 for size in files.values())
        and not any(p.is_dir() for p in out.iterdir())
    )

    bench = json.loads((out / "bench.json").read_text())
    assert bench["device"].startswith("CPU")
    measured = [row for row in bench["rows"] if "skipped" not in row]
    assert {(row["model"], row["precision"]) for row in measured} == {
        (m, p) for m in ("lite", "full") for p in ("fp32", "bf16")
    }
    assert all(row["skipped"] == "n/a: CUDA graphs need CUDA" for row in bench["rows"] if row["graphs"])
    assert [row["model"] for row in bench["accuracy"]] == ["lite", "full"]

    checkpoint = read_weights(out / "checkpoint.pt")
    shipped = read_weights(REPO / "model/weights/lite.pt")
    assert checkpoint["step"] == shipped["step"] + 2 and checkpoint["model_name"] == "lite"
    assert len(checkpoint["training"]["runs"]) == len(shipped["training"]["runs"]) + 1


def test_the_training_run_is_sized_to_end_its_decay_and_average_within_the_time_left(gpu_check):
    # 5 steps/s for 400 s: 90 % of 2,000 steps, the last 40 % of them decaying, 4 validations
    size = gpu_check.size_run(5.0, 400.0, gpu_check.GPU, ema_decay=0.999)
    assert (size.steps, size.decay_steps, size.checkpoint_every) == (1800, 720, 450)
    assert size.ema_decay == pytest.approx(1 - 4 / 1800)  # the average's horizon: a quarter of the run
    long_run = gpu_check.size_run(50.0, 400.0, gpu_check.GPU, ema_decay=0.999)
    assert long_run.steps == 18000 and long_run.ema_decay == 0.999  # never longer than the recipe's
    assert gpu_check.size_run(5.0, 400.0, gpu_check.GPU, ema_decay=0.0).ema_decay == 0.0  # off stays off
    capped = gpu_check.size_run(5.0, 400.0, gpu_check.CPU_SMOKE, ema_decay=0.999)
    assert capped.steps == gpu_check.CPU_SMOKE.train_steps


def test_stages_are_chosen_by_name_and_run_in_their_fixed_order(gpu_check):
    assert gpu_check.stage_list("train,environment") == ("environment", "train")
    with pytest.raises(argparse.ArgumentTypeError, match="stages are environment, tests"):
        gpu_check.stage_list("environment,warp")
