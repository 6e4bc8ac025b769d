"""The prepared GPU check (bench/gpu_check/) runs every stage end to end in its CPU smoke mode:
what a GPU machine will run, at tiny sizes, so that its first run there is not its first run."""

import argparse
import getpass
import importlib.util
import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from crestereo_pp.model.weights import read_weights
from crestereo_pp.training.config import TrainConfig
from shared_data import SMALL_STEREO_DEV_PAIR, STEREO_DEV

REPO = Path(__file__).resolve().parents[2]
STAGES = ("environment", "tests", "bench", "service", "probe", "train")  # what runs by default


@pytest.fixture
def bench_path(monkeypatch):
    """bench/ on the path: the package gpu_check and the sibling scripts it imports, as its stages run."""
    monkeypatch.syspath_prepend(str(REPO / "bench"))


def test_without_fastapi_the_service_stage_is_skipped_saying_so(bench_path, monkeypatch):
    from gpu_check.plans import GPU
    from gpu_check.stages.service import service_stage

    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None if name == "fastapi" else real_find_spec(name))
    result = service_stage(GPU, 0.0, None, None)
    assert (result.status, result.detail) == ("skipped", "skipped: fastapi not installed (carry wheels: --wheels)")


def smoke_run(out: Path, *options: str) -> str:
    """`bench/gpu_check --cpu-smoke OPTIONS --out OUT` run as a GPU machine runs it: its summary.md,
    once it has exited 0 leaving nothing in its temporary folder (its scratch training runs hold a
    checkpoint each)."""
    command = [sys.executable, "bench/gpu_check", "--cpu-smoke", *options, "--out", str(out)]
    temporary = out.parent / f"{out.name}-tmp"
    temporary.mkdir()
    # torch.compile's own cache stays where it was (torch's default is under the temporary folder)
    inductor = os.environ.get(
        "TORCHINDUCTOR_CACHE_DIR", str(Path(tempfile.gettempdir()) / f"torchinductor_{getpass.getuser()}")
    )
    environment = os.environ | {"TMPDIR": str(temporary), "TORCHINDUCTOR_CACHE_DIR": inductor}
    completed = subprocess.run(command, cwd=REPO, env=environment, capture_output=True, text=True, timeout=420)
    summary = (out / "summary.md").read_text()
    assert completed.returncode == 0, summary + completed.stderr[-3000:]
    assert sorted(path.name for path in temporary.iterdir()) == []
    return summary


def test_the_cpu_smoke_run_passes_every_stage_and_keeps_to_the_output_limits(tmp_path):
    out = tmp_path / "out"
    summary = smoke_run(out, "--adopt")
    assert summary.startswith("# GPU check: CPU smoke run (no GPU: no number here is a GPU number)")
    for stage in STAGES:
        assert f"| {stage} | passed |" in summary, summary

    files = {path.name: path.stat().st_size for path in out.iterdir()}
    assert {
        "gpu_check.log",
        "summary.md",
        "bench.json",
        "checkpoint.pt",
        "stable.pt",
        "log.csv",
        "loss_curve.png",
    } <= set(files)
    assert (
        len(files) <= 8
        and all(size < 16 * 2**20 for size in files.values())
        and not any(p.is_dir() for p in out.iterdir())
    )

    bench = json.loads((out / "bench.json").read_text())
    assert bench["device"].startswith("CPU")
    measured = [row for row in bench["rows"] if "skipped" not in row]
    assert {(row["model"], row["precision"], row["two_pass"]) for row in measured} == {
        (m, p, False) for m in ("lite", "full") for p in ("fp32", "bf16")
    } | {(m, "bf16", "auto") for m in ("lite", "full")}  # one pass as the paper times it, and the default
    assert all(row["skipped"] == "n/a: CUDA graphs need CUDA" for row in bench["rows"] if row["graphs"])
    assert [row["model"] for row in bench["accuracy"]] == ["lite", "full"]

    assert "## Training throughput (CPU)" in summary
    assert re.search(r"^\| lite \| batch1 \| batch 1, lr 1\.00e-04 \| [0-9.]+ \| 1\.00x \|", summary, re.MULTILINE), (
        summary
    )

    adopted = re.search(r'"adopted": "([\w-]+)"', summary)
    assert adopted is not None and f"| lite | {adopted.group(1)} |" in summary  # the training took a probe row
    assert re.search(r"^adopted row: [0-9.]+ steps/s", (out / "gpu_check.log").read_text(), re.MULTILINE)  # its rate

    checkpoint = read_weights(out / "checkpoint.pt")
    shipped = read_weights(REPO / "model/weights/lite.pt")
    assert checkpoint["step"] == shipped["step"] + 2 and checkpoint["model_name"] == "lite"
    assert len(checkpoint["training"]["runs"]) == len(shipped["training"]["runs"]) + 1

    # bench.json keeps the probe's rows: a later run adopts from them without probing again
    probed = {(row["model"], row["row"]) for row in bench["probe"]["rows"] if "skipped" not in row}
    assert ("lite", adopted.group(1)) in probed
    later = tmp_path / "later"
    later_summary = smoke_run(later, "--stages", "train", "--adopt", "--probe-from", str(out / "bench.json"))
    assert "| train | passed |" in later_summary and "| probe |" not in later_summary
    log = (later / "gpu_check.log").read_text()
    assert f"adopted the probe's row {adopted.group(1)} (CPU" in log and re.search(r"^adopted row: ", log, re.M)
    assert read_weights(later / "checkpoint.pt")["step"] == shipped["step"] + 2


def test_a_probe_from_file_without_probe_rows_is_refused_before_anything_runs(tmp_path):
    bench_only = tmp_path / "bench.json"
    bench_only.write_text(json.dumps({"device": "CPU", "rows": []}))
    out = tmp_path / "out"
    command = [sys.executable, "bench/gpu_check", "--cpu-smoke", "--adopt", "--probe-from", str(bench_only)]
    completed = subprocess.run([*command, "--out", str(out)], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert completed.returncode == 2 and f"--probe-from: {bench_only}: no probe rows there" in completed.stderr
    assert not out.exists()


def test_the_arms_stage_trains_a_candidate_and_the_recipe_for_equal_steps_and_scores_both(tmp_path):
    """Two dev pairs, one of them named as the Middlebury 2014 pairs are (scored apart too); the
    control is the probe row adopted, the candidate that row with its settings."""
    if not STEREO_DEV.is_dir():
        pytest.skip(f"real pairs not available: {STEREO_DEV} does not exist (see tests/shared_data.py)")
    data = tmp_path / "dev"
    data.mkdir()
    (data / SMALL_STEREO_DEV_PAIR).symlink_to(STEREO_DEV / SMALL_STEREO_DEV_PAIR)
    (data / "middlebury2014q_as_tsukuba").symlink_to(STEREO_DEV / SMALL_STEREO_DEV_PAIR)
    out = tmp_path / "out"
    arm = ["--arm", "thin_probability=1", "--arm", "flat_probability=0.5"]
    summary = smoke_run(out, "--stages", "probe,arms", "--adopt", *arm, "--data", str(data))
    assert "| arms | passed |" in summary, summary
    assert '## Arms: {"thin_probability": 1, "flat_probability": 0.5} against the recipe' in summary
    rows = re.findall(r"^\| (control|candidate) \| (\{.*?\}) \| (\d+) \| [0-9.]+ \| (.*) \|$", summary, re.MULTILINE)
    assert [row[0] for row in rows] == ["control", "candidate"], summary
    recipe = TrainConfig.from_dict(read_weights(REPO / "model/weights/lite.pt")["train_config"])
    assert json.loads(rows[0][1]) == {key: getattr(recipe, key) for key in ("thin_probability", "flat_probability")}
    assert json.loads(rows[1][1]) == {"thin_probability": 1, "flat_probability": 0.5}
    assert rows[0][2] == rows[1][2] == "2"  # equal steps, so equal pairs
    for row in rows:  # dev (2 pairs), apart (1), family (1 scene): EPE / bad-1 / bad-2 each
        assert re.fullmatch(
            r"[0-9.]+ / [0-9.]+ / [0-9.]+ \(2\) \| [0-9.]+ / [0-9.]+ / [0-9.]+ \(1\) \| "
            r"[0-9.]+ / [0-9.]+ / [0-9.]+ \(1\)",
            row[3],
        ), row[3]
    assert re.search(
        r"^Candidate against control, bad-2: dev [+-][0-9.]+ points \(EPE [+-][0-9.]+ px\), apart .*, family .*\.$",
        summary,
        re.MULTILINE,
    ), summary
    split = r"better on (\d), worse on (\d), level on (\d) of {} \(sign test p = [0-9.]+\)"
    each = re.search(
        r"^Pair by pair, the candidate's bad-2 against the control's: "
        + "; ".join(f"{name} {split.format(count)}" for name, count in (("dev", 2), ("apart", 1), ("family", 1)))
        + r"\.$",
        summary,
        re.MULTILINE,
    )
    assert each is not None, summary
    counts = [int(n) for n in each.groups()]
    assert [sum(counts[i : i + 3]) for i in (0, 3, 6)] == [2, 1, 1]
    for name in ("control", "candidate"):
        checkpoint = read_weights(out / f"arm-{name}.pt")
        assert checkpoint["step"] == read_weights(REPO / "model/weights/lite.pt")["step"] + 2
        assert read_weights(out / f"arm-{name}-stable.pt")["step"] < checkpoint["step"]  # where the decay began
    assert {path.name for path in out.iterdir()} == {
        "gpu_check.log",
        "summary.md",
        "bench.json",  # the probe's rows, for a later run's --probe-from
        *(f"arm-{name}{part}.pt" for name in ("control", "candidate") for part in ("", "-stable")),
    }


def test_the_arms_are_compared_pair_by_pair_with_an_exact_sign_test(bench_path):
    from gpu_check.report import pair_by_pair, sign_test

    assert sign_test(9, 1) == pytest.approx(22 / 1024)  # 2 * (C(10, 0) + C(10, 1)) / 2^10
    assert sign_test(5, 5) == sign_test(0, 0) == 1.0
    assert sign_test(16, 0) == pytest.approx(2 / 2**16)
    control, candidate = [10.0, 5.0, 7.5, 3.0], [9.0, 5.0, 8.0, 2.5]
    assert pair_by_pair(control, candidate) == "better on 2, worse on 1, level on 1 of 4 (sign test p = 1.00)"


def test_the_training_run_is_sized_to_end_its_decay_and_average_within_the_time_left(bench_path):
    from gpu_check.plans import CPU_SMOKE, GPU
    from gpu_check.stages.train import size_run

    # 5 steps/s for 400 s: 90 % of 2,000 steps, the last 40 % of them decaying, 4 validations
    size = size_run(5.0, 400.0, GPU, ema_decay=0.999)
    assert (size.steps, size.decay_steps, size.checkpoint_every) == (1800, 720, 450)
    assert size.ema_decay == pytest.approx(1 - 4 / 1800)  # the average's horizon: a quarter of the run
    long_run = size_run(50.0, 400.0, GPU, ema_decay=0.999)
    assert long_run.steps == 18000 and long_run.ema_decay == 0.999  # never longer than the recipe's
    assert size_run(5.0, 400.0, GPU, ema_decay=0.0).ema_decay == 0.0  # off stays off
    capped = size_run(5.0, 400.0, CPU_SMOKE, ema_decay=0.999)
    assert capped.steps == CPU_SMOKE.train_steps


def test_stages_are_chosen_by_name_and_run_in_their_fixed_order(bench_path):
    from gpu_check.orchestrator import stage_list

    assert stage_list("train,environment") == ("environment", "train")
    with pytest.raises(argparse.ArgumentTypeError, match="stages are environment, tests"):
        stage_list("environment,warp")


def test_the_throughput_probe_scales_the_batch_and_the_lr_by_its_square_root_then_tries_the_options(bench_path):
    from train_speed import probe_rows

    rows = probe_rows(16, 2e-4, (1, 2, 4, 8), options=True, compiled=True)
    assert [row.name for row in rows] == [
        "batch16",
        "batch32",
        "batch64",
        "batch128",
        "foreach-adamw",
        "channels-last",
        "compile",
        "cuda-graphs",
    ]
    assert [row.overrides["batch_size"] for row in rows[:4]] == [16, 32, 64, 128]
    assert [row.overrides["lr"] for row in rows[:4]] == pytest.approx([2e-4, 2.828e-4, 4e-4, 5.657e-4], rel=1e-3)
    assert rows[-1].overrides == {
        "batch_size": 64,
        "lr": pytest.approx(4e-4),
        "compile": True,
        "compile_mode": "reduce-overhead",
    }
    assert [row.name for row in probe_rows(2, 1e-4, (1, 2), options=True, compiled=False)] == [
        "batch2",
        "batch4",
        "foreach-adamw",
        "channels-last",
    ]


def test_training_settings_are_given_as_json_values_or_plain_text(bench_path):
    from gpu_check.orchestrator import parse_arguments

    args = parse_arguments(["--train-set", "batch_size=64", "--train-set", "schedule=constant"])
    assert args.train_set == [("batch_size", 64), ("schedule", "constant")]
    assert parse_arguments(["--train-set", "train_iters=[2,4,8]"]).train_set == [("train_iters", [2, 4, 8])]
    with pytest.raises(SystemExit):
        parse_arguments(["--train-set", "batch_size"])


def test_the_training_recipe_is_the_campaigns_data_with_each_models_own_iterations(bench_path):
    from gpu_check.orchestrator import parse_arguments
    from gpu_check.plans import GPU
    from gpu_check.recipe import recipe_of

    args = parse_arguments(["--train-set", "batch_size=64"])
    full = recipe_of("full", GPU, args)
    lite = recipe_of("lite", GPU, args)
    shipped = read_weights(REPO / "model/weights/lite.pt")["train_config"]
    assert (full.model, lite.model) == ("full", "lite")
    assert full.train_iters is None and lite.train_iters is None  # each network's own counts
    assert full.max_disparity == lite.max_disparity == shipped["max_disparity"]
    assert (full.crop_height, full.crop_width, full.batch_size, full.device) == (384, 512, 64, "cuda")


def test_adoption_takes_the_row_that_trains_the_most_pairs_in_the_time_left(bench_path):
    from gpu_check.stages.train import adopted_row

    rows = [
        {"model": "lite", "row": "batch16", "pairs_per_s": 40.0, "first_step_s": 2.0},
        {"model": "lite", "row": "batch64", "pairs_per_s": 120.0, "first_step_s": 3.0},
        {"model": "lite", "row": "compile", "pairs_per_s": 200.0, "first_step_s": 150.0},
        {"model": "lite", "row": "batch128", "skipped": "OutOfMemoryError: CUDA out of memory"},
        {"model": "full", "row": "batch16", "pairs_per_s": 500.0, "first_step_s": 1.0},
    ]
    assert adopted_row(rows, "lite", 300.0)["row"] == "batch64"  # 120 x 297 > 200 x 150
    assert adopted_row(rows, "lite", 600.0)["row"] == "compile"  # 200 x 450 > 120 x 597
    assert adopted_row(rows[3:4], "lite", 600.0) is None


@pytest.fixture(scope="module")
def packed_dev_pairs(tmp_path_factory):
    """The real dev pairs packed as the prepared GPU run carries them (`--pack-data`)."""
    if not STEREO_DEV.is_dir():
        pytest.skip(f"real pairs not available: {STEREO_DEV} does not exist (see tests/shared_data.py)")
    sys.path.insert(0, str(REPO / "bench"))
    try:
        from gpu_check.pairs import pack_dev_pairs
    finally:
        sys.path.remove(str(REPO / "bench"))
    archive = tmp_path_factory.mktemp("packed") / "stereo-dev.tar.gz"
    pack_dev_pairs(STEREO_DEV, archive)
    return archive


def test_the_checkout_and_the_packed_dev_pairs_fit_in_what_travels_to_the_gpu_machine(bench_path, packed_dev_pairs):
    """The prepared run carries the dev pairs packed beside the checkout; weights files or images
    added to the tree can push both past the device's limit, and the lease is refused at its start."""
    from gpu_check.plans import MAX_TRAVEL_BYTES

    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=REPO,
        capture_output=True,
        check=True,
    ).stdout.split(b"\0")
    files = [REPO / name.decode() for name in listed if name]
    checkout = sum(path.stat().st_size for path in files if path.is_file())
    packed = packed_dev_pairs.stat().st_size
    left = MAX_TRAVEL_BYTES - checkout - packed
    assert left >= 0, (
        f"checkout {checkout / 2**20:.1f} MiB + packed dev pairs {packed / 2**20:.1f} MiB: {-left / 2**20:.1f} over"
    )


def test_packed_dev_pairs_unpack_on_the_gpu_machine_to_the_same_pairs(bench_path, packed_dev_pairs, tmp_path):
    from gpu_check.pairs import dev_pairs

    from crestereo_pp.stereo_data.readers import open_dataset

    folder = dev_pairs(packed_dev_pairs, tmp_path)
    assert folder is not None and folder.parent == tmp_path
    unpacked, original = open_dataset(folder), open_dataset(STEREO_DEV)
    assert [files.name for files in unpacked.files] == [files.name for files in original.files]
    assert len(unpacked) == 16
    for index in (0, len(original) - 1):
        a, b = unpacked[index], original[index]
        assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
        assert np.array_equal(a.disparity, b.disparity) and np.array_equal(a.valid, b.valid)


def test_the_probe_measures_every_models_eager_rows_before_any_compiled_row(bench_path):
    """A compile takes minutes on a fresh machine: it must not leave full's rows unmeasured."""
    from types import SimpleNamespace

    from gpu_check.plans import GPU
    from gpu_check.stages.probe import probe_order

    recipe = SimpleNamespace(batch_size=16, lr=2e-4)
    order = [(model, row.name) for model, row in probe_order(GPU, {"lite": recipe, "full": recipe}, compiled=True)]
    compiled = [(model, name) for model in ("lite", "full") for name in ("compile", "cuda-graphs")]
    eager = [(model, f"batch{16 * factor}") for model in ("lite", "full") for factor in (1, 2, 4, 8)]
    eager[4:4] = [("lite", "foreach-adamw"), ("lite", "channels-last")]
    assert order == eager + compiled
