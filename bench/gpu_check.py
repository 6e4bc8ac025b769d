"""The prepared GPU check: one command for a GPU machine lent for minutes, where nothing can be
debugged. Stages, each in its own process and each guarded (a failure or a timeout is recorded
and the next stage runs), within one time budget:

    environment  torch, the device, nvidia-smi
    tests        the CUDA tests (tests/gpu, the CUDA test of stereo_data)
    bench        inference table: lite and full at 384x1248, batch 1 and 8, fp32 and
                 bf16, eager and CUDA-graph replay (StereoPredictor.predict_batch, as the service
                 runs it); then bf16 against fp32 and graph against eager on the dev pairs
    service      `python -m crestereo_pp.service` on loopback with CRESTEREO_DEVICE=cuda: a real pair over HTTP,
                 concurrent requests (batches), both models; skipped when fastapi is missing
    probe        training throughput, lite and full: pairs/s and peak memory of the training step at
                 batch 1x-8x the recipe's, plain AdamW, channels-last, torch.compile and CUDA graphs
                 (bench/train_speed.py's `measure` and `probe_rows`), at most two minutes
    train        --model (lite) from --weights (its shipped file) for the minutes left: a short
                 probe run measures the step rate, then one run sized to end its flat-decay schedule
                 (and its weight average's horizon) within the time left; a checkpoint with an
                 optimiser state is resumed, a weights-only file starts a fresh optimiser

    python3 bench/gpu_check.py --out DIR [--minutes 9] [--stages S,...] [--data DIR] [--wheels DIR]
                               [--model lite|full] [--weights FILE] [--train-set KEY=VALUE ...]
                               [--train-compile]
    python3 bench/gpu_check.py --cpu-smoke --out DIR    # the same stages on the CPU, tiny

DIR (or $GPU_CHECK_OUT, else $OUT) receives at most 8 files, each under 16 MiB: gpu_check.log
(every stage's output), summary.md (stage results and tables), bench.json (the benchmark's
numbers) and the training run's checkpoint.pt, log.csv, loss_curve.png (validation.csv with dev
pairs). --data: the real dev pairs (NAME/{left.png,right.png,disp.pfm}); by default $STEREO_DEV,
shared/data/stereo-dev in the checkout or beside it, else procedural scenes stand in. --wheels: a
folder of wheels (fastapi, uvicorn, ...) installed with pip --no-index for the service stage; by
default .whl/ in the checkout when present. Needs only the standard library in this process; the
stages need torch, numpy, OpenCV, httpx and the project. Exit status 0 when no stage failed.
"""

from __future__ import annotations

import argparse
import collections
import datetime as dt
import importlib.util
import itertools
import json
import os
import platform
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from train_speed import GPU_RECIPE  # bench/'s sibling script (standard library only at import)

if TYPE_CHECKING:
    from crestereo_pp.model.config import ModelName

REPO = Path(__file__).resolve().parents[1]

RESUME_DIR = REPO / "training" / "resume"
"""The stable branch of each model's last GPU run (its stable.pt), committed beside the shipped
weights so that the next run goes on at the peak lr (warmup-stable-decay)."""
STAGES = ("environment", "tests", "bench", "service", "probe", "train")
MAX_FILES = 8
MAX_FILE_BYTES = 16 * 2**20
BF16_TOLERANCE_PX = 0.05
"""bf16 is usable where its disparities are within this mean distance of fp32's (issue 11)."""
ROW_SECONDS = 5.0
"""A benchmark row stops timing after this long once it has MIN_TIMED_CALLS calls."""
MIN_TIMED_CALLS = 3
SERVICE_PACKAGES = {
    "fastapi": "fastapi",
    "uvicorn": "uvicorn",
    "pydantic": "pydantic",
    "python_multipart": "python-multipart",
    "httpx": "httpx",
    "prometheus_client": "prometheus-client",
}
"""Modules the service stage needs (module -> package), beyond torch and the project."""


@dataclass(frozen=True)
class Plan:
    """What the stages do: the real check on a GPU, or the CPU smoke run with tiny sizes.

    iters: inference iterations of the benchmark (None: each model's own); warmup_calls: untimed
    predict_batch calls before each timed row (3 with graphs: eager, capture, replay);
    stage_seconds: the most each stage may take (train: what is left of `minutes`);
    reserve_seconds: kept for the stages after it, so that an overrun cannot starve them.
    train: TrainConfig overrides of the shipped lite checkpoint's config for the training stage,
    which runs `train_steps` more steps at most; probe_steps: the untimed-then-timed steps of the
    probe run that measures the step rate; decay_fraction: the share of the run's steps over which
    flat-decay brings the lr to 0; train_tail_seconds: kept after the training time for the last
    validation, the checkpoint and the process's start; throughput_steps: timed steps per row of the
    throughput probe (of throughput_models, at throughput_factors times the recipe's batch, after
    throughput_warmup untimed steps), which stops a row after throughput_row_seconds and starts
    none with less left.
    """

    device: str
    minutes: float
    tests: tuple[str, ...]
    models: tuple[ModelName, ...]
    sizes: tuple[tuple[int, int], ...]
    batches: tuple[int, ...]
    iters: tuple[int, int, int] | None
    warmup_calls: int
    timed_runs: int
    accuracy_pairs: int
    service_models: tuple[str, ...]
    service_requests: int
    stage_seconds: dict[str, float]
    reserve_seconds: dict[str, float]
    train: dict[str, Any]
    train_steps: int
    probe_steps: int
    decay_fraction: float
    train_tail_seconds: float
    throughput_models: tuple[ModelName, ...]
    throughput_factors: tuple[int, ...]
    throughput_warmup: int
    throughput_steps: int
    throughput_row_seconds: float
    label: str = ""


GPU = Plan(
    device="cuda",
    minutes=9.0,
    tests=("tests/gpu", "tests/stereo_data/test_synthetic_scenes.py::test_generator_runs_and_is_deterministic_on_cuda"),
    models=("lite", "full"),
    sizes=((384, 1248),),
    batches=(1, 8),
    iters=None,
    warmup_calls=3,
    timed_runs=20,
    accuracy_pairs=4,
    service_models=("lite", "full"),
    service_requests=16,
    stage_seconds={"environment": 60, "tests": 150, "bench": 90, "service": 120, "probe": 120},
    reserve_seconds={"environment": 420, "tests": 330, "bench": 150, "service": 90, "probe": 120},
    train=dict(GPU_RECIPE, log_every=25),  # the weights' recipe (scenes, max disparity, iterations) on the GPU step
    train_steps=1_000_000,
    probe_steps=40,
    decay_fraction=0.4,
    train_tail_seconds=75,
    throughput_models=("lite", "full"),
    throughput_factors=(1, 2, 4, 8),
    throughput_warmup=2,
    throughput_steps=8,
    throughput_row_seconds=8.0,
    label="GPU",
)
CPU_SMOKE = Plan(
    device="cpu",
    minutes=5.0,  # what the stages need on a quiet machine is about one minute; a busy one needs room
    tests=("tests/gpu/test_cuda_graphs.py", "tests/gpu/test_cuda_paths.py"),
    models=("lite", "full"),
    sizes=((32, 64),),
    batches=(1, 2),
    iters=(1, 1, 1),
    warmup_calls=1,
    timed_runs=2,
    accuracy_pairs=1,
    service_models=("lite",),
    service_requests=3,
    stage_seconds={"environment": 30, "tests": 90, "bench": 90, "service": 60, "probe": 60},
    reserve_seconds={"environment": 60, "tests": 50, "bench": 40, "service": 30, "probe": 20},
    train=dict(
        crop_height=64,
        crop_width=96,
        max_disparity=32.0,
        batch_size=1,
        train_iters=(1, 1, 1),
        lr=1e-4,
        schedule="flat-decay",
        warmup_fraction=0.0,
        log_every=1,
        num_workers=0,
    ),
    train_steps=2,
    probe_steps=2,
    decay_fraction=0.4,
    train_tail_seconds=20,
    throughput_models=("lite",),
    throughput_factors=(1, 2),
    throughput_warmup=1,
    throughput_steps=1,
    throughput_row_seconds=2.0,
    label="CPU smoke run (no GPU: no number here is a GPU number)",
)


@dataclass
class StageResult:
    """How a stage ended: status "passed" | "failed" | "skipped" | "timed out", its wall
    seconds, one line of detail, and its numbers (`data`, JSON-ready)."""

    status: str
    detail: str = ""
    seconds: float = 0.0
    data: dict[str, Any] = field(default_factory=dict)


# ---------------------------------------------------------------------------------------------
# The orchestrating process: standard library only (a CUDA error cannot reach it).


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_arguments(argv)
    plan = CPU_SMOKE if args.cpu_smoke else GPU
    if args.minutes is not None:
        plan = replace(plan, minutes=args.minutes)
    if args.stage is not None:
        return run_stage_here(args, plan)
    out = output_folder(args.out)
    data = args.data if args.cpu_smoke else dev_pairs(args.data)  # the smoke run's pairs are tiny scenes
    with tempfile.TemporaryDirectory(prefix="gpu-check-") as scratch, (out / "gpu_check.log").open("w") as log:
        package = package_tree(Path(scratch) / "package")  # the project importable as crestereo_pp
        environment = {**os.environ, "PYTHONPATH": package, "PYTHONUNBUFFERED": "1"}
        service_path = [package]  # the wheels reach the service stage only
        wheels = args.wheels or (REPO / ".whl" if (REPO / ".whl").is_dir() else None)
        if wheels is not None:
            service_path.insert(0, install_wheels(wheels, Path(scratch) / "site", log))
        environments = {stage: environment for stage in STAGES}
        environments["service"] = {**environment, "PYTHONPATH": os.pathsep.join(service_path)}
        results = run_stages(plan, args, out, data, Path(scratch), environments, log)
    print((out / "summary.md").read_text(), flush=True)
    return 0 if all(r.status in ("passed", "skipped") for r in results.values()) else 1


def package_tree(dest: Path) -> str:
    """`dest`, holding `crestereo_pp/` as links into this checkout (tools/package_tree.py): the stages
    import the project as installed without installing it (this machine's Python has no index)."""
    subprocess.run(
        [sys.executable, str(REPO / "tools" / "package_tree.py"), str(dest)], check=True, capture_output=True
    )
    return str(dest)


def run_stages(
    plan: Plan,
    args: argparse.Namespace,
    out: Path,
    data: Path | None,
    scratch: Path,
    environments: dict[str, Any],
    log: Any,
) -> dict[str, StageResult]:
    """Every stage in turn (in environments[stage]), each within its share of the time left; the
    summary after each."""
    deadline = time.monotonic() + 60.0 * plan.minutes
    results: dict[str, StageResult] = {}
    for stage in args.stages:
        remaining = deadline - time.monotonic()
        if stage == "train":
            seconds = remaining - 10.0
        else:
            seconds = min(plan.stage_seconds[stage], remaining - plan.reserve_seconds[stage])
        print(f"{stage}: at most {seconds:.0f} s", flush=True)
        log.write(f"\n===== {stage} ({seconds:.0f} s at most) =====\n")
        log.flush()
        if seconds < 5:
            result = StageResult("skipped", "no time left")
        elif stage == "tests":
            result = run_tests(plan, seconds, environments[stage], log)
        else:
            result_file = scratch / f"{stage}.json"
            command = [sys.executable, str(Path(__file__).resolve()), "--stage", stage, "--out", str(out)]
            command += ["--seconds", f"{seconds:.0f}", "--result", str(result_file)]
            command += ["--cpu-smoke"] * args.cpu_smoke + ["--train-compile"] * args.train_compile
            command += ["--model", args.model] + (["--weights", str(args.weights)] if args.weights else [])
            command += [f"--train-set={key}={json.dumps(value)}" for key, value in args.train_set]
            command += ["--adopt"] * args.adopt + ["--probe-result", str(scratch / "probe.json")]
            command += ["--data", str(data)] if data is not None else []
            result = run_child(command, seconds, environments[stage], log, result_file)
        results[stage] = result
        line = f"{stage}: {result.status} in {result.seconds:.1f} s: {result.detail}"
        print(line, flush=True)
        log.write(f"----- {line}\n")
        log.flush()
        if stage == "bench" and result.data.get("rows"):
            (out / "bench.json").write_text(json.dumps(result.data, indent=1))
        write_summary(out, plan, data, results)
    return results


def parse_arguments(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, help="output folder [$GPU_CHECK_OUT, else $OUT]")
    parser.add_argument("--cpu-smoke", action="store_true", help="the same stages on the CPU, tiny sizes")
    parser.add_argument("--minutes", type=float, help="time budget of all stages [9; smoke: 5]")
    parser.add_argument(
        "--stages",
        type=stage_list,
        default=STAGES,
        help=f"the stages to run, comma-separated, in this order [{','.join(STAGES)}]",
    )
    parser.add_argument("--data", type=Path, help="dev pairs [$STEREO_DEV, shared/data/stereo-dev]")
    parser.add_argument("--wheels", type=Path, help="wheels to install for the service stage [.whl/]")
    parser.add_argument("--model", choices=("lite", "full"), default="lite", help="the network to train [lite]")
    parser.add_argument("--weights", type=Path, help="the weights to train from [model/weights/MODEL.pt]")
    parser.add_argument(
        "--train-set",
        type=train_setting,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a TrainConfig field of the training stage (VALUE as JSON, else text), e.g. batch_size=64; repeatable",
    )
    parser.add_argument("--train-compile", action="store_true", help="torch.compile the training step")
    parser.add_argument(
        "--adopt",
        action="store_true",
        help="the training stage takes the probe's best setting for --model: the row that trains the most "
        "pairs in the time left (its pairs/s times that time less its first step, where compiling shows)",
    )
    parser.add_argument("--probe-result", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--stage", choices=STAGES, help=argparse.SUPPRESS)  # child mode
    parser.add_argument("--seconds", type=float, help=argparse.SUPPRESS)
    parser.add_argument("--result", type=Path, help=argparse.SUPPRESS)
    return parser.parse_args(argv)


def train_setting(text: str) -> tuple[str, Any]:
    """--train-set KEY=VALUE: the field name and its value (JSON where it parses, else the text)."""
    key, equals, value = text.partition("=")
    if not equals or not key.strip():
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    try:
        return key.strip(), json.loads(value)
    except json.JSONDecodeError:
        return key.strip(), value


def stage_list(text: str) -> tuple[str, ...]:
    """--stages: a comma-separated subset of STAGES, run in STAGES' order."""
    names = {name.strip() for name in text.split(",") if name.strip()}
    unknown = names - set(STAGES)
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"stages are {', '.join(STAGES)}; got {text!r}")
    return tuple(stage for stage in STAGES if stage in names)


def output_folder(given: Path | None) -> Path:
    """The --out folder, else $GPU_CHECK_OUT, else $OUT (the device machine's return folder)."""
    name = given or os.environ.get("GPU_CHECK_OUT") or os.environ.get("OUT")
    if not name:
        raise SystemExit("gpu_check: name the output folder with --out DIR (or GPU_CHECK_OUT)")
    folder = Path(name)
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def dev_pairs(given: Path | None) -> Path | None:
    """The folder of real dev pairs to use, or None (procedural scenes stand in)."""
    candidates = [
        given,
        os.environ.get("STEREO_DEV"),
        REPO / "shared/data/stereo-dev",
        REPO.parent / "shared/data/stereo-dev",
    ]
    return next((Path(c) for c in candidates if c and Path(c).is_dir()), None)


def install_wheels(wheels: Path, target: Path, log: Any) -> str:
    """pip-install the wheels of `wheels` (no index, no dependencies) into `target`."""
    files = sorted(str(p) for p in wheels.glob("*.whl"))
    log.write(f"installing {len(files)} wheels from {wheels} into {target}\n")
    log.flush()
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "-q",
            "--no-index",
            "--no-deps",
            "--no-compile",
            "--target",
            str(target),
            *files,
        ],
        stdout=log,
        stderr=subprocess.STDOUT,
        check=False,
    )
    return str(target)


def run_logged(
    command: list[str], seconds: float, environment: dict[str, str], log: Any
) -> tuple[int | None, list[str]]:
    """Run `command` in a process group of its own, its output copied to `log` as it comes; kill
    the whole group after `seconds`. Returns the exit status (None: killed) and the last lines."""
    process = subprocess.Popen(
        command,
        cwd=REPO,
        env=environment,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        errors="replace",
        start_new_session=True,
    )
    tail: collections.deque[str] = collections.deque(maxlen=40)

    def copy() -> None:
        assert process.stdout is not None
        for line in process.stdout:
            log.write(line)
            log.flush()
            tail.append(line.rstrip("\n"))

    reader = threading.Thread(target=copy, daemon=True)
    reader.start()
    try:
        status: int | None = process.wait(timeout=seconds)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
        status = None
    reader.join(timeout=10)
    return status, list(tail)


def run_tests(plan: Plan, seconds: float, environment: dict[str, str], log: Any) -> StageResult:
    """pytest on plan.tests; its last line (the counts) is the detail."""
    start = time.monotonic()
    command = [sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider", *plan.tests]
    status, tail = run_logged(command, seconds, environment, log)
    outcome = "timed out" if status is None else "passed" if status == 0 else "failed"
    return StageResult(outcome, tail[-1].strip("= ") if tail else "no output", time.monotonic() - start)


def run_child(
    command: list[str], seconds: float, environment: dict[str, str], log: Any, result_file: Path
) -> StageResult:
    """Run a stage in a child process; its result is what it last wrote to `result_file`."""
    start = time.monotonic()
    status, tail = run_logged(command, seconds, environment, log)
    result = StageResult("failed", tail[-1] if tail else "no output")
    if result_file.is_file():
        result = StageResult(**json.loads(result_file.read_text()))
    if status is None:
        result.status, result.detail = "timed out", f"killed after {seconds:.0f} s; {result.detail}"
    elif status != 0 and result.status not in ("failed", "skipped"):
        result.status, result.detail = "failed", f"exit status {status}; {result.detail}"
    result.seconds = time.monotonic() - start
    return result


# ---------------------------------------------------------------------------------------------
# The report.


def write_summary(out: Path, plan: Plan, data: Path | None, results: dict[str, StageResult]) -> None:
    environment = results.get("environment", StageResult("skipped")).data
    lines = [
        f"# GPU check: {plan.label}",
        "",
        f"{dt.datetime.now(dt.UTC).isoformat(timespec='seconds')}, budget {plan.minutes:g} min; "
        f"device: {environment.get('device', '?')}; torch {environment.get('torch', '?')}; "
        f"Python {platform.python_version()}; dev pairs: {data or 'none (procedural scenes)'}",
        "",
        "| stage | status | seconds | detail |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| {name} | {r.status} | {r.seconds:.0f} | {r.detail.replace('|', '/')} |" for name, r in results.items()
    ]
    if "bench" in results:
        lines += ["", *bench_tables(results["bench"].data)]
    if "service" in results and results["service"].data:
        lines += ["", "## Service", "", "```", json.dumps(results["service"].data, indent=1), "```"]
    if "probe" in results and results["probe"].data:
        lines += ["", *probe_table(results["probe"].data)]
    if "train" in results and results["train"].data:
        lines += ["", "## Training", "", "```", json.dumps(results["train"].data, indent=1), "```"]
    lines += ["", *output_files_report(out)]
    (out / "summary.md").write_text("\n".join(lines) + "\n")


def bench_tables(data: dict[str, Any]) -> list[str]:
    """Markdown: the speed table (one row per model, size, batch, precision, graphs) and the
    accuracy table (one row per model)."""
    lines = [
        f"## Inference ({data.get('device', '?')})",
        "",
        "`StereoPredictor.predict_batch` end to end (uint8 arrays in, numpy maps out, as the service "
        f"calls it), median of the timed calls after {data.get('warmup_calls')} untimed ones; iterations "
        f"{data.get('iters') or 'of each model'}; procedural scenes.",
        "",
        "| model | size | batch | precision | CUDA graph | ms / batch | ms / pair | pairs / s | peak MiB | replays |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in data.get("rows", []):
        graphs = "yes" if row["graphs"] else "no"
        head = f"| {row['model']} | {row['size']} | {row['batch']} | {row['precision']} | {graphs} |"
        if "skipped" in row:
            lines.append(f"{head} {row['skipped']} | | | | |")
        else:
            lines.append(
                f"{head} {row['ms_per_batch']:.2f} | {row['ms_per_pair']:.2f} | {row['pairs_per_s']:.1f} | "
                f"{row['peak_mib'] if row['peak_mib'] is not None else '-'} | {row['replays']} |"
            )
    lines += [
        "",
        f"bf16 against fp32 (eager) and graph replay against eager (fp32), per pair, mean over pairs; "
        f"bf16 is usable where the mean |difference| is within {BF16_TOLERANCE_PX} px.",
        "",
        "| model | pairs | source | mean abs bf16 - fp32 px | within tolerance | max abs graph - eager px "
        "| EPE fp32 | EPE bf16 |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in data.get("accuracy", []):
        graph = "-" if row["graph_max_abs_px"] is None else f"{row['graph_max_abs_px']:.4f}"
        lines.append(
            f"| {row['model']} | {row['pairs']} | {row['source']} | {row['bf16_mean_abs_px']:.4f} | "
            f"{'yes' if row['bf16_mean_abs_px'] <= BF16_TOLERANCE_PX else 'NO'} | {graph} | "
            f"{row['epe_fp32']:.3f} | {row['epe_bf16']:.3f} |"
        )
    return lines


def output_files_report(out: Path) -> list[str]:
    files = sorted(p for p in out.iterdir() if p.is_file())
    verdict = "within" if len(files) <= MAX_FILES and all(p.stat().st_size < MAX_FILE_BYTES for p in files) else "OVER"
    lines = [f"## Output files: {len(files)} ({verdict} the limit of {MAX_FILES} files under 16 MiB each)", ""]
    lines += [f"- {p.name}: {p.stat().st_size / 2**20:.2f} MiB" for p in files]
    return lines


# ---------------------------------------------------------------------------------------------
# The stages, each in a child process of its own.


def run_stage_here(args: argparse.Namespace, plan: Plan) -> int:
    """Child mode: run one stage, writing its StageResult to args.result (also while running)."""

    def save(result: StageResult) -> None:
        args.result.write_text(json.dumps(result.__dict__))

    stages: dict[str, Callable[..., StageResult]] = {
        "environment": environment_stage,
        "bench": bench_stage,
        "service": service_stage,
        "probe": probe_stage,
        "train": train_stage,
    }
    deadline = time.monotonic() + args.seconds
    result = stages[args.stage](plan, deadline, args, save)
    save(result)
    return 0 if result.status in ("passed", "skipped") else 1


def environment_stage(plan: Plan, deadline: float, args: argparse.Namespace, save: Callable[..., None]) -> StageResult:
    import torch

    data: dict[str, Any] = {
        "torch": torch.__version__,
        "python": platform.python_version(),
        "cuda": torch.version.cuda,
        "device": "cpu",
    }
    print(
        f"torch {torch.__version__} (CUDA {torch.version.cuda}), Python {platform.python_version()}, "
        f"{os.cpu_count()} CPUs, CUDA available: {torch.cuda.is_available()}"
    )
    if torch.cuda.is_available():
        properties = torch.cuda.get_device_properties(0)
        data.update(
            device=properties.name,
            capability=f"{properties.major}.{properties.minor}",
            memory_gib=round(properties.total_memory / 2**30, 1),
            multiprocessors=properties.multi_processor_count,
        )
        print(json.dumps(data))
        if shutil.which("nvidia-smi"):
            subprocess.run(["nvidia-smi"], check=False)
    if plan.device == "cuda" and not torch.cuda.is_available():
        return StageResult("failed", "no CUDA device: run with --cpu-smoke on a machine without one", data=data)
    return StageResult("passed", f"{data['device']}, torch {torch.__version__}", data=data)


def samples_for(data_dir: Path | None, count: int, height: int, width: int, device: Any) -> tuple[list[Any], str]:
    """`count` pairs with ground truth (StereoSample, host arrays): the dev pairs, or procedural
    scenes of height x width rendered on `device`. Returns them and what they are."""
    import numpy as np
    import torch

    from crestereo_pp.stereo_data.readers import StereoSample, open_dataset
    from crestereo_pp.stereo_data.synthetic import SceneConfig, SceneGenerator

    if data_dir is not None:
        dataset = open_dataset(data_dir)
        return [dataset[i] for i in range(min(count, len(dataset)))], f"dev pairs ({data_dir.name})"
    generator = SceneGenerator(SceneConfig(height=height, width=width, max_disparity=width / 6.0), device=device)
    scenes = generator.generate(batch_size=count, seed=11)

    def image(batch: torch.Tensor, index: int) -> np.ndarray:
        return batch[index].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).cpu().numpy()

    samples = []
    for i in range(count):
        valid = scenes.valid[i, 0].cpu().numpy()
        disparity = np.where(valid, scenes.disparity[i, 0].cpu().numpy(), np.inf).astype(np.float32)
        samples.append(StereoSample(f"scene{i}", image(scenes.left, i), image(scenes.right, i), disparity, valid, None))
    return samples, f"procedural scenes {height}x{width}"


def bench_stage(plan: Plan, deadline: float, args: argparse.Namespace, save: Callable[..., None]) -> StageResult:
    import torch

    from crestereo_pp.model import load_model

    device = torch.device(plan.device)
    on_cuda = device.type == "cuda"
    data: dict[str, Any] = {
        "device": torch.cuda.get_device_name(device) if on_cuda else f"CPU ({os.cpu_count()} cores)",
        "iters": plan.iters,
        "warmup_calls": plan.warmup_calls,
        "rows": [],
        "accuracy": [],
    }
    for name in plan.models:
        eager = load_model(name, device=device, cuda_graphs=False)
        graphed = load_model(name, device=device) if on_cuda else None
        for height, width in plan.sizes:
            samples, _ = samples_for(None, max(plan.batches), height, width, device)
            for batch, graphs, precision in itertools.product(plan.batches, (False, True), ("fp32", "bf16")):
                row: dict[str, Any] = dict(model=name, size=f"{height}x{width}", batch=batch, precision=precision)
                row["graphs"] = graphs
                if time.monotonic() > deadline - 20:
                    row["skipped"] = "not measured: out of time"
                else:
                    row.update(bench_row(plan, eager, graphed, graphs, precision, samples[:batch]))
                data["rows"].append(row)
                print(json.dumps(row), flush=True)
                save(StageResult("running", f"{len(data['rows'])} rows", data=data))
        if time.monotonic() < deadline - 20:
            data["accuracy"].append(accuracy(plan, name, eager, graphed, args.data, deadline))
            print(json.dumps(data["accuracy"][-1]), flush=True)
        del eager, graphed
        if on_cuda:
            torch.cuda.empty_cache()
    measured = [r for r in data["rows"] if "skipped" not in r]
    late = [r for r in data["rows"] if r.get("skipped", "").startswith("not measured")]
    complete = not late and len(data["accuracy"]) == len(plan.models)
    detail = f"{len(measured)} of {len(data['rows'])} rows measured; accuracy of {len(data['accuracy'])} models"
    return StageResult("passed" if complete and measured else "failed", detail, data=data)


def bench_row(plan: Plan, eager: Any, graphed: Any, graphs: bool, precision: str, samples: list[Any]) -> dict[str, Any]:
    """One row's numbers (see time_predict_batch), or why there are none. A graphed row's graphs
    are dropped after it, so that each row's peak memory is its own."""
    if not graphs:
        return time_predict_batch(eager, precision, [s.left for s in samples], [s.right for s in samples], plan)
    if graphed is None:
        return {"skipped": "n/a: CUDA graphs need CUDA"}
    numbers = time_predict_batch(graphed, precision, [s.left for s in samples], [s.right for s in samples], plan)
    graphed.graphs.clear()
    return numbers


def time_predict_batch(
    predictor: Any, precision: str, lefts: list[Any], rights: list[Any], plan: Plan
) -> dict[str, Any]:
    """Median wall time of up to plan.timed_runs calls of predict_batch(lefts, rights) at
    `precision` (after plan.warmup_calls; at least MIN_TIMED_CALLS, then while under
    ROW_SECONDS), peak device memory, and how many of the timed calls replayed a CUDA graph."""
    import torch

    predictor.precision = precision
    on_cuda = predictor.device.type == "cuda"
    if on_cuda:
        torch.cuda.reset_peak_memory_stats(predictor.device)
    for _ in range(plan.warmup_calls):
        predictor.predict_batch(lefts, rights, iters=plan.iters)
    replays_before = predictor.graphs.replays if predictor.graphs is not None else 0
    times: list[float] = []
    least = min(MIN_TIMED_CALLS, plan.timed_runs)
    while len(times) < plan.timed_runs and (len(times) < least or sum(times) < ROW_SECONDS):
        start = time.perf_counter()
        predictor.predict_batch(lefts, rights, iters=plan.iters)  # numpy out: the copy to the host waits
        times.append(time.perf_counter() - start)
    median_s = statistics.median(times)
    return dict(
        ms_per_batch=1000 * median_s,
        ms_per_pair=1000 * median_s / len(lefts),
        pairs_per_s=len(lefts) / median_s,
        peak_mib=round(torch.cuda.max_memory_allocated(predictor.device) / 2**20) if on_cuda else None,
        replays=f"{(predictor.graphs.replays - replays_before) if predictor.graphs is not None else 0}/{len(times)}",
    )


def accuracy(plan: Plan, name: str, eager: Any, graphed: Any, data_dir: Path | None, deadline: float) -> dict[str, Any]:
    """bf16 against fp32 and graph replay against eager on the dev pairs (or procedural scenes)."""
    import numpy as np

    height, width = plan.sizes[0]
    samples, source = samples_for(data_dir, plan.accuracy_pairs, height, width, eager.device)
    bf16_differences: list[float] = []
    graph_differences: list[float] = []
    epe_fp32: list[float] = []
    epe_bf16: list[float] = []
    for sample in samples:
        if bf16_differences and time.monotonic() > deadline - 20:
            break
        known = sample.valid & np.isfinite(sample.disparity)
        eager.precision = "fp32"
        fp32 = eager.predict(sample.left, sample.right, iters=plan.iters).disparity
        eager.precision = "bf16"
        bf16 = eager.predict(sample.left, sample.right, iters=plan.iters).disparity
        bf16_differences.append(float(np.abs(bf16 - fp32).mean()))
        epe_fp32.append(float(np.abs(fp32 - sample.disparity)[known].mean()))
        epe_bf16.append(float(np.abs(bf16 - sample.disparity)[known].mean()))
        if graphed is not None:
            graphed.precision = "fp32"
            for _ in range(2):  # the second sighting of the shape is captured and replayed
                replayed = graphed.predict_batch([sample.left], [sample.right], iters=plan.iters)[0].disparity
            graph_differences.append(float(np.abs(replayed - fp32).max()))
            graphed.graphs.clear()
    return dict(
        model=name,
        pairs=len(bf16_differences),
        source=source,
        bf16_mean_abs_px=float(np.mean(bf16_differences)),
        graph_max_abs_px=max(graph_differences) if graph_differences else None,
        epe_fp32=float(np.mean(epe_fp32)),
        epe_bf16=float(np.mean(epe_bf16)),
    )


def service_stage(plan: Plan, deadline: float, args: argparse.Namespace, save: Callable[..., None]) -> StageResult:
    missing = [package for module, package in SERVICE_PACKAGES.items() if importlib.util.find_spec(module) is None]
    if missing:
        return StageResult("skipped", f"skipped: {', '.join(missing)} not installed (carry wheels: --wheels)")
    from crestereo_pp.client import StereoClient
    from crestereo_pp.service.local import start_service

    origins = {module: getattr(importlib.util.find_spec(module), "origin", None) for module in SERVICE_PACKAGES}
    print(f"service packages from: {origins}", flush=True)
    height, width = plan.sizes[0]
    sample = samples_for(args.data, 1, height, width, "cpu")[0][0]

    settings = {
        "CRESTEREO_DEVICE": plan.device,
        "CRESTEREO_MODELS": ",".join(plan.service_models),
        "CRESTEREO_MAX_BATCH_PIXELS": str(8 * 480 * 1248),
        "CRESTEREO_LOG_LEVEL": "warning",
    }
    try:
        server = start_service(settings, ready_timeout_s=max(1.0, deadline - 15 - time.monotonic()))
    except RuntimeError as error:
        return StageResult("failed", f"the service did not become ready ({error})")
    try:
        timeout_s = max(10.0, deadline - time.monotonic())
        with StereoClient(server.base_url, timeout_s=timeout_s, max_retries=0) as client:
            data = exchange(client, plan, sample)
    finally:
        server.stop()
    problems = data.pop("problems")
    detail = f"{data['requests']} requests on {plan.device}, batch sizes {data['batch_sizes']}"
    return StageResult("failed" if problems else "passed", "; ".join(problems) or detail, data=data)


def exchange(client: Any, plan: Plan, sample: Any) -> dict[str, Any]:
    """Requests to the ready service through `client` (a `client.StereoClient`): one per model,
    then `service_requests` concurrent lite ones; checks each answer (shapes, finite non-negative
    disparity, uncertainty in [0, 1])."""
    from concurrent.futures import ThreadPoolExecutor

    import numpy as np

    from crestereo_pp.client import ServiceError

    known = sample.valid & np.isfinite(sample.disparity)
    iters = tuple(plan.iters) if plan.iters else None
    problems: list[str] = []
    epe: dict[str, float] = {}
    compute_ms: dict[str, list[float]] = collections.defaultdict(list)
    batch_sizes: list[int] = []

    def ask(model: str) -> None:
        try:
            result = client.disparity(sample.left, sample.right, model=model, iters=iters)
        except ServiceError as error:
            problems.append(f"{model}: HTTP {error.status} {error.code}: {error.message[:200]}")
            return
        disparity, uncertainty = result.disparity, result.uncertainty
        if disparity.shape != sample.disparity.shape or uncertainty.shape != disparity.shape:
            problems.append(f"{model}: maps of shape {disparity.shape}, not {sample.disparity.shape}")
        elif not (np.isfinite(disparity).all() and (disparity >= 0).all() and disparity.std() > 0):
            problems.append(f"{model}: disparity not finite, negative or constant")
        elif not ((uncertainty >= 0) & (uncertainty <= 1)).all():
            problems.append(f"{model}: uncertainty outside [0, 1]")
        else:
            epe[model] = round(float(np.abs(disparity - sample.disparity)[known].mean()), 3)
        compute_ms[model].append(result.compute_ms)
        batch_sizes.append(result.batch_size)

    for model in plan.service_models:
        for _ in range(2):  # the second request of a shape replays a CUDA graph
            ask(model)
    with ThreadPoolExecutor(plan.service_requests) as pool:
        list(pool.map(ask, [plan.service_models[0]] * plan.service_requests))
    return dict(
        pair=sample.name,
        size=list(sample.disparity.shape),
        requests=len(batch_sizes),
        batch_sizes=sorted(set(batch_sizes)),
        epe_px=epe,
        compute_ms={m: [round(t, 1) for t in times] for m, times in compute_ms.items()},
        problems=problems,
    )


@dataclass(frozen=True)
class RunSize:
    """The training run that fits the time left: `steps` more steps, flat-decay over the last
    `decay_steps` of them, a validation and checkpoint every `checkpoint_every`, and the weight
    average's decay `ema_decay` (its horizon, 1 / (1 - decay) steps, a quarter of the run at most)."""

    steps: int
    decay_steps: int
    checkpoint_every: int
    ema_decay: float


def size_run(steps_per_second: float, seconds: float, plan: Plan, ema_decay: float) -> RunSize:
    """Size the run to `seconds` at the probe's `steps_per_second` (10 % kept for the validations
    along the way), at most plan.train_steps; `ema_decay` is the recipe's, shortened for short runs."""
    steps = max(1, min(plan.train_steps, int(0.9 * steps_per_second * seconds)))
    return RunSize(
        steps=steps,
        decay_steps=max(1, round(plan.decay_fraction * steps)),
        checkpoint_every=max(1, steps // 4),
        ema_decay=0.0 if ema_decay == 0 else min(ema_decay, max(0.9, 1.0 - 4.0 / steps)),
    )


def median_rate(rows: list[dict[str, str]]) -> float:
    """The median pairs/s of a training log's rows (its windows), the first (warm-up, autotuning)
    left out where there are more."""
    rates = [float(row["pairs_per_second"]) for row in rows]
    return statistics.median(rates[1:] or rates)


def weights_for(model: str, args: argparse.Namespace) -> Path:
    """The weights file a stage trains `model` from: --weights for the --model, else the stable
    branch of its last GPU run (training/resume/MODEL.pt, where one was kept), else the shipped file."""
    from crestereo_pp.model.weights import WEIGHTS_DIR

    if args.weights is not None and model == args.model:
        return Path(args.weights)
    stable = RESUME_DIR / f"{model}.pt"
    return stable if stable.is_file() else WEIGHTS_DIR / f"{model}.pt"


def recipe_of(model: ModelName, plan: Plan, args: argparse.Namespace) -> Any:
    """The TrainConfig of a stage's training step for `model`: the data recipe of the shipped lite
    weights (scenes, disparities, photometry: what the campaign settled on) with the model's own
    iterations, then the plan's step (plan.train), --train-compile and --train-set."""
    from crestereo_pp.model.weights import WEIGHTS_DIR, read_weights
    from crestereo_pp.training.config import TrainConfig

    return replace(
        TrainConfig.from_dict(read_weights(WEIGHTS_DIR / "lite.pt")["train_config"]),
        **{"train_iters": None, **plan.train, "compile": args.train_compile, **dict(args.train_set)},
        model=model,
        device=plan.device,
    )


def probe_stage(plan: Plan, deadline: float, args: argparse.Namespace, save: Callable[..., None]) -> StageResult:
    """Training throughput: bench/train_speed.py's probe rows for each model, in one process; a row
    that fails (out of memory, a compile error) is recorded and the next runs."""
    import torch
    from train_speed import measure, probe_rows

    device = torch.device(plan.device)
    on_cuda = device.type == "cuda"
    data: dict[str, Any] = {"device": torch.cuda.get_device_name(device) if on_cuda else "CPU", "rows": []}
    scratch = Path(tempfile.mkdtemp(prefix="probe-"))
    for model in plan.throughput_models:
        weights = weights_for(model, args)
        recipe = replace(recipe_of(model, plan, args), out_dir=str(scratch), val_data=None)
        rows = probe_rows(
            recipe.batch_size, recipe.lr, plan.throughput_factors, options=model == "lite", compiled=on_cuda
        )
        last_seconds, last_batch = 0.0, 1  # the wall time of the model's previous row, and its batch
        for row in rows:
            entry: dict[str, Any] = {"model": model, "row": row.name, "setting": row.description}
            entry["overrides"] = row.overrides
            expected = max(plan.throughput_row_seconds, last_seconds * row.overrides["batch_size"] / last_batch)
            started = time.monotonic()
            if deadline - started < expected + 5:
                entry["skipped"] = "no time left"
            else:
                try:
                    entry |= measure(
                        replace(recipe, **row.overrides),
                        weights,
                        device,
                        plan.throughput_steps,
                        max_seconds=plan.throughput_row_seconds,
                        warmup_steps=plan.throughput_warmup,
                    )
                except Exception as error:  # out of memory, a compile failure: the next row still runs
                    entry["skipped"] = f"{type(error).__name__}: {str(error)[:160]}"
                finally:
                    torch._dynamo.reset()
                    if on_cuda:
                        torch.cuda.empty_cache()
                last_seconds, last_batch = time.monotonic() - started, row.overrides["batch_size"]
            print(json.dumps(entry), flush=True)
            data["rows"].append(entry)
            save(StageResult("passed", f"{len(data['rows'])} rows", data=data))  # kept if the stage is killed
    measured = [row for row in data["rows"] if "skipped" not in row]
    status = "passed" if measured else "failed"
    return StageResult(status, f"{len(measured)} of {len(data['rows'])} rows measured", data=data)


def probe_table(data: dict[str, Any]) -> list[str]:
    """Markdown: one row per model and setting; `vs recipe` is pairs/s against the model's first row."""
    lines = [
        f"## Training throughput ({data.get('device', '?')})",
        "",
        "Median seconds per optimiser step after two untimed steps (the batch made on the device included; "
        "`data ms` of it); the first step's seconds show compilation; lr scaled by the square root of the "
        "batch ratio.",
        "",
        "| model | row | setting | pairs / s | vs recipe | step ms | data ms | first step s | peak GiB |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    recipe: dict[str, float] = {}
    for row in data.get("rows", []):
        head = f"| {row['model']} | {row['row']} | {row['setting']} |"
        if "skipped" in row:
            lines.append(f"{head} {row['skipped'].replace('|', '/')} | | | | | |")
            continue
        base = recipe.setdefault(row["model"], row["pairs_per_s"])
        peak = "-" if row["peak_gib"] is None else f"{row['peak_gib']:.1f}"
        lines.append(
            f"{head} {row['pairs_per_s']:.1f} | {row['pairs_per_s'] / base:.2f}x | {1000 * row['step_s']:.0f} | "
            f"{1000 * row['data_s']:.0f} | {row['first_step_s']:.1f} | {peak} |"
        )
    return lines


def adopted_row(rows: list[dict[str, Any]], model: str, seconds: float) -> dict[str, Any] | None:
    """The probe row that trains `model` on the most pairs in `seconds`: pairs/s times the seconds
    left after its first step (compilation); None without a measured row."""
    measured = [row for row in rows if row["model"] == model and "skipped" not in row]
    if not measured:
        return None
    return max(measured, key=lambda row: row["pairs_per_s"] * max(0.0, seconds - row["first_step_s"]))


def train_stage(plan: Plan, deadline: float, args: argparse.Namespace, save: Callable[..., None]) -> StageResult:
    import torch

    from crestereo_pp.model.weights import network_from_weights, read_weights, weights_of, write_weights
    from crestereo_pp.training.config import TrainConfig
    from crestereo_pp.training.records import read_csv
    from crestereo_pp.training.trainer import STABLE_NAME, train, validate

    shipped = weights_for(args.model, args)
    saved = read_weights(shipped)
    if saved.get("model_name") != args.model:
        return StageResult("failed", f"{shipped} holds {saved.get('model_name')!r} weights, not {args.model!r}")
    resumable = "optimizer" in saved  # else a weights-only file: a fresh optimiser from step 0
    source = {"resume": shipped} if resumable else {"init_weights": shipped}
    first_step = int(saved["step"]) if resumable else 0
    recipe = recipe_of(args.model, plan, args)
    adopted = None
    if args.adopt and args.probe_result is not None and args.probe_result.is_file():
        probe_rows_seen = json.loads(args.probe_result.read_text())["data"].get("rows", [])
        adopted = adopted_row(probe_rows_seen, args.model, deadline - time.monotonic())
        if adopted is not None:
            recipe = replace(recipe, **adopted["overrides"])
            print(f"adopted the probe's row {adopted['row']}: {adopted['setting']}", flush=True)

    def rate_run(config: TrainConfig) -> float:
        """Train plan.probe_steps steps into a scratch folder; the step rate after the first window."""
        folder = Path(tempfile.mkdtemp(prefix="probe-"))
        log_every = max(1, plan.probe_steps // 4)
        trial = replace(
            config,
            out_dir=str(folder),
            max_steps=first_step + plan.probe_steps,
            schedule_steps=first_step + plan.probe_steps + 1,
            decay_steps=1,
            max_minutes=1.5,
            log_every=log_every,
            checkpoint_every=10**9,
            val_data=None,
        )
        train(trial, **source, progress=False)
        return median_rate(read_csv(folder / "log.csv")) / config.batch_size

    start = time.monotonic()
    try:
        steps_per_second = rate_run(recipe)
    except Exception as error:  # a lent GPU is minutes long: retry once in the plainest setting, not never
        print(f"probe failed ({type(error).__name__}: {error}); again in fp32 with plain AdamW", flush=True)
        recipe = replace(recipe, precision="fp32", fused_adamw="off")
        steps_per_second = rate_run(recipe)
    probe_seconds = time.monotonic() - start
    seconds = deadline - time.monotonic() - plan.train_tail_seconds
    size = size_run(steps_per_second, seconds, plan, recipe.ema_decay)
    last_step = first_step + size.steps
    config = replace(
        recipe,
        out_dir=str(args.out),
        max_steps=last_step,
        schedule_steps=last_step,
        decay_steps=size.decay_steps,
        checkpoint_every=size.checkpoint_every,
        ema_decay=size.ema_decay,
        max_minutes=max(0.05, seconds / 60.0),
        val_data=str(args.data) if args.data is not None else None,
    )
    print(
        f"probe: {steps_per_second:.2f} steps/s in {probe_seconds:.0f} s; training {args.model} from {shipped} "
        f"(step {first_step}) for {size.steps} steps, at most {seconds / 60.0:.2f} min: {json.dumps(config.to_dict())}",
        flush=True,
    )
    start_dev = None
    if config.val_data is not None:  # the starting point, as the run's validations measure it
        start_dev = validate(network_from_weights(saved, args.model).to(plan.device), config, torch.device(plan.device))
    result = train(config, **source, progress=False)
    rows = read_csv(args.out / "log.csv")
    compacted = []
    for path in (result.checkpoint, args.out / STABLE_NAME):
        if path.is_file() and path.stat().st_size >= MAX_FILE_BYTES:  # full's training state does not fit
            write_weights(weights_of(read_weights(path), half=True), path)
            compacted.append(path.name)
    data: dict[str, Any] = dict(
        model=args.model,
        weights=str(shipped),
        adopted=None if adopted is None else adopted["row"],
        resumed=resumable,
        steps=result.step - first_step,
        planned_steps=size.steps,
        probe_steps_per_s=round(steps_per_second, 2),
        pairs_per_s_median=round(median_rate(rows), 1),
        batch_size=config.batch_size,
        crop=f"{config.crop_height}x{config.crop_width}",
        lr=config.lr,
        decay_steps=size.decay_steps,
        ema_decay=size.ema_decay,
        compile=config.compile,
        bf16=config.precision == "bf16" or (config.precision == "auto" and plan.device == "cuda"),
        final_loss=float(rows[-1]["loss"]),
        final_train_epe=float(rows[-1]["train_epe"]),
        peak_gib=round(torch.cuda.max_memory_allocated() / 2**30, 1) if plan.device == "cuda" else None,
        checkpoint_mib=round(result.checkpoint.stat().st_size / 2**20, 1),
        stable_step=read_weights(args.out / STABLE_NAME)["step"] if (args.out / STABLE_NAME).is_file() else None,
        weights_only_fp16=compacted,
    )
    if start_dev is not None:
        data["start_dev"] = {k: round(v, 3) for k, v in start_dev.items() if k in ("epe", "bad1", "bad2")}
    validation = read_csv(args.out / "validation.csv")
    if validation:
        data["dev"] = [
            {k: float(v) for k, v in row.items() if k in ("step", "epe", "bad1", "bad2")} for row in validation
        ]
    print(json.dumps(data))
    return StageResult("passed", f"{data['steps']} steps, {data['pairs_per_s_median']} pairs/s", data=data)


if __name__ == "__main__":
    sys.exit(main())
