"""The orchestrating process: standard library only, so that a CUDA error cannot reach it. It parses
the options, lays out the project as a link tree (tools/package_tree.py), installs the carried
wheels, runs each stage in turn (`tests` as pytest, the others as `python -P -m gpu_check --stage
NAME`, each a child process with bench/ and the link tree on its PYTHONPATH) and rewrites the
summary after each. In a child (`--stage`) it runs that one stage."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from . import __doc__ as USAGE
from .pairs import DEV_ARCHIVE, dev_pairs, pack_dev_pairs
from .plans import BENCH, CPU_SMOKE, DEFAULT_STAGES, GPU, REPO, STAGES, Plan, StageResult
from .report import write_summary
from .runner import run_child
from .stages.arms import arms_stage
from .stages.bench import bench_stage
from .stages.environment import environment_stage
from .stages.probe import probe_stage
from .stages.service import service_stage
from .stages.tests import run_tests
from .stages.train import train_stage
from .wheels import install_wheels


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_arguments(argv)
    plan = CPU_SMOKE if args.cpu_smoke else GPU
    if args.minutes is not None:
        plan = replace(plan, minutes=args.minutes)
    if args.stage is not None:
        return run_stage_here(args, plan)
    if args.pack_data:
        return pack_data(args.data)
    out = output_folder(args.out)
    with tempfile.TemporaryDirectory(prefix="gpu-check-") as scratch, (out / "gpu_check.log").open("w") as log:
        # The smoke run's pairs are tiny scenes; packed dev pairs are unpacked into the scratch folder.
        data = args.data if args.cpu_smoke else dev_pairs(args.data, Path(scratch))
        # The project importable as crestereo_pp, and bench/: this package and its sibling scripts.
        path = [package_tree(Path(scratch) / "package"), str(BENCH)]
        environment = {**os.environ, "PYTHONPATH": os.pathsep.join(path), "PYTHONUNBUFFERED": "1"}
        wheels = args.wheels or (REPO / ".whl" if (REPO / ".whl").is_dir() else None)
        if wheels is not None:  # the wheels reach the service stage only
            path.insert(0, install_wheels(wheels, Path(scratch) / "site", log))
        environments = {stage: environment for stage in STAGES}
        environments["service"] = {**environment, "PYTHONPATH": os.pathsep.join(path)}
        results = run_stages(plan, args, out, data, Path(scratch), environments, log)
    print((out / "summary.md").read_text(), flush=True)
    return 0 if all(r.status in ("passed", "skipped") for r in results.values()) else 1


def pack_data(given: Path | None) -> int:
    """--pack-data: the dev pairs found here packed as DEV_ARCHIVE, to travel with the checkout."""
    folder = dev_pairs(given)
    if folder is None:
        raise SystemExit("gpu_check: no dev pairs found to pack (--data DIR, or $STEREO_DEV)")
    size = pack_dev_pairs(folder, DEV_ARCHIVE)
    print(f"packed {folder} as {DEV_ARCHIVE} ({size / 2**20:.1f} MiB)")
    return 0


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
    if args.probe_from is not None:  # an earlier run's probe, in the shape the probe stage leaves (which replaces it)
        (scratch / "probe.json").write_text(json.dumps({"data": args.probe_from}))
    for stage in args.stages:
        remaining = deadline - time.monotonic()
        if stage in ("train", "arms"):
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
            command = [sys.executable, "-P", "-m", "gpu_check", "--stage", stage, "--out", str(out)]
            command += ["--seconds", f"{seconds:.0f}", "--result", str(result_file)]
            command += ["--cpu-smoke"] * args.cpu_smoke + ["--train-compile"] * args.train_compile
            command += ["--model", args.model] + (["--weights", str(args.weights)] if args.weights else [])
            command += [f"--train-set={key}={json.dumps(value)}" for key, value in args.train_set]
            command += [f"--arm={key}={json.dumps(value)}" for key, value in args.arm]
            command += ["--adopt"] * args.adopt + ["--probe-result", str(scratch / "probe.json")]
            command += ["--data", str(data)] if data is not None else []
            result = run_child(command, seconds, environments[stage], log, result_file)
        results[stage] = result
        line = f"{stage}: {result.status} in {result.seconds:.1f} s: {result.detail}"
        print(line, flush=True)
        log.write(f"----- {line}\n")
        log.flush()
        numbers = returned_numbers(results)
        if numbers:
            (out / "bench.json").write_text(json.dumps(numbers, indent=1))
        write_summary(out, plan, data, results)
    return results


def returned_numbers(results: dict[str, StageResult]) -> dict[str, Any]:
    """bench.json: the bench stage's numbers, and under "probe" the probe stage's (what a later run's
    --probe-from adopts from), each where its stage measured rows."""
    numbers: dict[str, Any] = {}
    if "bench" in results and results["bench"].data.get("rows"):
        numbers |= results["bench"].data
    if "probe" in results and results["probe"].data.get("rows"):
        numbers["probe"] = results["probe"].data
    return numbers


def earlier_probe(text: str) -> dict[str, Any]:
    """--probe-from FILE: the probe stage's numbers in an earlier run's bench.json (`returned_numbers`)."""
    try:
        probe = json.loads(Path(text).read_text())["probe"]
        rows = probe["rows"]
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise argparse.ArgumentTypeError(f"{text}: no probe rows there ({type(error).__name__}: {error})") from None
    if not isinstance(rows, list) or not rows:
        raise argparse.ArgumentTypeError(f"{text}: no probe rows there")
    return dict(probe)


def parse_arguments(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="gpu_check", description=USAGE, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, help="output folder [$GPU_CHECK_OUT, else $OUT]")
    parser.add_argument("--cpu-smoke", action="store_true", help="the same stages on the CPU, tiny sizes")
    parser.add_argument("--minutes", type=float, help="time budget of all stages [9; smoke: 5]")
    parser.add_argument(
        "--stages",
        type=stage_list,
        default=DEFAULT_STAGES,
        help=f"the stages to run, comma-separated, in this order: {','.join(STAGES)} [{','.join(DEFAULT_STAGES)}]",
    )
    parser.add_argument(
        "--data",
        type=Path,
        help="dev pairs: a folder, or one packed by --pack-data [$STEREO_DEV, shared/data/stereo-dev, "
        "then shared/stereo-dev.tar.gz]",
    )
    parser.add_argument(
        "--pack-data",
        action="store_true",
        help="pack the dev pairs found (as --data) as shared/stereo-dev.tar.gz, which travels with the checkout "
        "to the GPU machine, and exit",
    )
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
        "--arm",
        type=train_setting,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="the arms stage's candidate: a TrainConfig field it sets on the recipe (as --train-set), e.g. "
        "room_probability=0.5; repeatable. The control trains the recipe for as many pairs from the same weights",
    )
    parser.add_argument(
        "--adopt",
        action="store_true",
        help="the training stage takes the probe's best setting for --model: the row that trains the most "
        "pairs in the time left (its pairs/s times that time less its first step, where compiling shows)",
    )
    parser.add_argument(
        "--probe-from",
        type=earlier_probe,
        metavar="FILE",
        help="an earlier run's bench.json: --adopt takes its probe rows where this run runs no probe stage "
        "(the training's own decay moves forward where that rate is not reached)",
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
        "arms": arms_stage,
    }
    deadline = time.monotonic() + args.seconds
    result = stages[args.stage](plan, deadline, args, save)
    save(result)
    return 0 if result.status in ("passed", "skipped") else 1
