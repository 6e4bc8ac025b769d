"""Inference speed of lite and full per backend and precision on this machine, beside SGBM.

    python bench/model_speed.py [--runs 5] [--rounds 1] [--models lite full] [--sizes 384x1248 480x640 256x512]
                                [--backends torch openvino] [--precisions fp32 bf16] [--profile]

Prints the CPU's bf16 support and the measured fp32 matmul GFLOP/s, then per model, size,
backend and precision: median latency over --runs runs, its speed-up over torch fp32 at that
size (measured in the same run), counted model FLOPs (torch.utils.flop_counter on the torch row:
convolutions and matrix products; grid_sample and elementwise work are not counted) and the
GFLOP/s they make, the OpenVINO graph's preparation time (its export, or reading it from the
cache) and the first call's time (OpenVINO compiles the shape there), and peak memory; then
OpenCV SGBM on the same pairs. Each row runs in a fresh child process, so that its peak RSS is its
own. torch rows with bf16 run under autocast. Each timing is the network's one pass
(``two_pass=False``, ``NETWORK_ONLY``: the SGBM rows time the matcher
the default blends with); the default ``two_pass="auto"`` adds a pass at quarter resolution, and either a
half-resolution one for pairs with large disparities or, for pairs with small ones, runs the pass
on the pair enlarged up to 1.5x (``crestereo-pp eval`` times the default).
--profile adds the torch rows' top operators.

--rounds R runs a model and size's rows R times, interleaved (torch fp32, torch bf16, OpenVINO
fp32, OpenVINO bf16, then again), each time in a fresh process; the median is then over all R x
runs timings of a row, so that a machine whose speed drifts (a shared VM) moves every row alike
and the ratios stay fair. Prepare and first call are the first round's, peak RSS the largest.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
import warnings
from typing import Any

import numpy as np
import torch
from timing import timed_calls  # bench/'s sibling script
from torch.utils.flop_counter import FlopCounterMode

from crestereo_pp.evaluation.sgbm import sgbm_disparity
from crestereo_pp.inference import NETWORK_ONLY, load_model
from crestereo_pp.inference.backend_choice import Backend, Precision
from crestereo_pp.inference.openvino_backend import native_bf16
from crestereo_pp.model.config import MODEL_NAMES


def matmul_gflops(n: int = 2048, runs: int = 10) -> float:
    """Median fp32 GFLOP/s of an n x n x n matmul with all intra-op threads."""
    a, b = torch.randn(n, n), torch.randn(n, n)
    torch.mm(a, b)
    times = timed_calls(lambda: torch.mm(a, b), runs)
    return 2 * n**3 / statistics.median(times) / 1e9


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def measure(
    name: str, height: int, width: int, backend: Backend, precision: Precision, runs: int, profile: bool
) -> dict[str, Any]:
    """One model at one size on one backend and precision, in this process."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # random weights time the same as trained ones
        predictor = load_model(name, backend=backend, precision=precision)
    left = torch.rand(1, 3, height, width) * 255
    right = torch.rand(1, 3, height, width) * 255
    start = time.perf_counter()
    if not predictor.prepare():
        raise RuntimeError(f"{name} could not be prepared on {backend}")
    prepare_s = time.perf_counter() - start

    def one_pass() -> None:
        """The network once at the pair's size: no quick pass, no enlarging, no host refinement."""
        predictor.predict(left, right, two_pass=False, **NETWORK_ONLY)

    start = time.perf_counter()
    if backend == "torch":
        with FlopCounterMode(display=False) as counter:
            one_pass()  # the warm-up
        gflop: float | None = counter.get_total_flops() / 1e9
    else:
        one_pass()  # the warm-up, which compiles the shape
        gflop = None
    first_call_s = time.perf_counter() - start
    times = timed_calls(one_pass, runs)
    result = {
        "times_s": times,
        "gflop": gflop,
        "prepare_s": prepare_s,
        "first_call_s": first_call_s,
        "peak_rss_mib": peak_rss_mib(),
    }
    if profile and backend == "torch":
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
            one_pass()
        result["profile"] = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=15)
    return result


def sgbm_seconds(height: int, width: int, runs: int) -> float:
    """Median seconds of OpenCV SGBM (the evaluation's baseline, with its left-right check) on a
    random pair, disparities up to a quarter of the width (at most 192 px)."""
    rng = np.random.default_rng(0)
    left = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    right = np.ascontiguousarray(np.roll(left, -8, axis=1))
    times = timed_calls(lambda: sgbm_disparity(left, right, float(min(192, width // 4))), runs + 1)
    return statistics.median(times[1:])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--models", nargs="+", default=list(MODEL_NAMES))
    parser.add_argument("--sizes", nargs="+", default=["384x1248", "480x640", "256x512"])
    parser.add_argument("--backends", nargs="+", choices=["torch", "openvino"], default=["torch", "openvino"])
    parser.add_argument("--precisions", nargs="+", choices=["fp32", "bf16"], default=["fp32", "bf16"])
    parser.add_argument("--profile", action="store_true")
    parser.add_argument("--one", help=argparse.SUPPRESS)  # child mode: "model:HxW:backend:precision"
    args = parser.parse_args()

    if args.one:
        name, size, backend, precision = args.one.split(":")
        height, width = map(int, size.split("x"))
        print(json.dumps(measure(name, height, width, backend, precision, args.runs, args.profile)))
        return

    rate = matmul_gflops()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} intra-op threads; native bf16: {native_bf16()}")
    print(f"fp32 matmul (2048^3): {rate:.1f} GFLOP/s\n")
    print(
        "| model | size | backend | precision | median latency (s) | vs torch fp32 | GFLOP/s | prepare (s) "
        "| first call (s) | peak RSS (MiB) |"
    )
    print("|" + "---|" * 10)
    profiles = []
    for name in args.models:
        for size in args.sizes:
            rows = [(backend, precision) for backend in args.backends for precision in args.precisions]
            results: dict[tuple[str, str], list[dict[str, Any]]] = {row: [] for row in rows}
            for _ in range(args.rounds):
                for backend, precision in rows:
                    command = [sys.executable, __file__, "--one", f"{name}:{size}:{backend}:{precision}"]
                    command += ["--runs", str(args.runs)] + (["--profile"] if args.profile else [])
                    done = subprocess.run(command, check=True, capture_output=True, text=True)
                    results[backend, precision].append(json.loads(done.stdout))
            reference: float | None = None
            gflop: float | None = None
            for backend, precision in rows:
                rounds = results[backend, precision]
                first = rounds[0]
                median_s = statistics.median(t for r in rounds for t in r["times_s"])
                gflop = first["gflop"] or gflop
                if (backend, precision) == ("torch", "fp32"):
                    reference = median_s
                ratio = f"{reference / median_s:.2f}x" if reference else "-"
                achieved = f"{gflop / median_s:.1f}" if gflop else "-"
                peak = max(r["peak_rss_mib"] for r in rounds)
                print(
                    f"| {name} | {size} | {backend} | {precision} | {median_s:.3f} | {ratio} | {achieved} | "
                    f"{first['prepare_s']:.1f} | {first['first_call_s']:.2f} | {peak:.0f} |",
                    flush=True,
                )
                if "profile" in first:
                    profiles.append((f"{name} {size}", first["profile"]))
    for size in args.sizes:
        height, width = map(int, size.split("x"))
        print(f"| SGBM | {size} | OpenCV | - | {sgbm_seconds(height, width, args.runs):.3f} | | | | | |", flush=True)
    for title, table in profiles:
        print(f"\n## profile: {title}\n{table}")


if __name__ == "__main__":
    main()
