"""Inference speed of lite and full on this machine, against its own fp32 matmul rate.

    python bench/model_speed.py [--runs 5] [--models lite full] [--sizes 384x1248 480x640] [--profile]

Prints the measured fp32 matmul GFLOP/s, then per model and size: median latency over --runs
runs after one warm-up, counted model FLOPs (torch.utils.flop_counter: convolutions and matrix
products; grid_sample and elementwise work are not counted), achieved GFLOP/s, its ratio to the
matmul rate, and peak memory. Each (model, size) runs in a fresh child process so that its
peak RSS is its own. --profile adds the top operators by CPU time (torch.profiler).
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
from pathlib import Path

import torch
from torch.utils.flop_counter import FlopCounterMode

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing
from model import load_model  # noqa: E402
from model.config import MODEL_NAMES  # noqa: E402


def matmul_gflops(n: int = 2048, runs: int = 10) -> float:
    """Median fp32 GFLOP/s of an n x n x n matmul with all intra-op threads."""
    a, b = torch.randn(n, n), torch.randn(n, n)
    torch.mm(a, b)
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        torch.mm(a, b)
        times.append(time.perf_counter() - start)
    return 2 * n**3 / statistics.median(times) / 1e9


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def measure(name: str, height: int, width: int, runs: int, profile: bool) -> dict:
    """One model at one size, in this process."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # random weights time the same as trained ones
        predictor = load_model(name)
    left = torch.rand(1, 3, height, width) * 255
    right = torch.rand(1, 3, height, width) * 255
    rss_loaded = peak_rss_mib()
    with FlopCounterMode(display=False) as counter:
        predictor.predict(left, right)  # also the warm-up
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        predictor.predict(left, right)
        times.append(time.perf_counter() - start)
    result = {
        "model": name,
        "size": f"{height}x{width}",
        "median_s": statistics.median(times),
        "gflop": counter.get_total_flops() / 1e9,
        "peak_rss_mib": peak_rss_mib(),
        "rss_increase_mib": peak_rss_mib() - rss_loaded,
    }
    if profile:
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
            predictor.predict(left, right)
        result["profile"] = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=15)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--models", nargs="+", default=list(MODEL_NAMES))
    parser.add_argument("--sizes", nargs="+", default=["384x1248", "480x640"])
    parser.add_argument("--profile", action="store_true")
    parser.add_argument("--one", help=argparse.SUPPRESS)  # child mode: "model:HxW"
    args = parser.parse_args()

    if args.one:
        name, size = args.one.split(":")
        height, width = map(int, size.split("x"))
        print(json.dumps(measure(name, height, width, args.runs, args.profile)))
        return

    rate = matmul_gflops()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} intra-op threads")
    print(f"fp32 matmul (2048^3): {rate:.1f} GFLOP/s\n")
    header = "| model | size | median latency (s) | GFLOP | GFLOP/s | of matmul | peak RSS (MiB) | RSS increase (MiB) |"
    print(header)
    print("|" + "---|" * 8)
    profiles = []
    for name in args.models:
        for size in args.sizes:
            command = [sys.executable, __file__, "--one", f"{name}:{size}", "--runs", str(args.runs)]
            if args.profile:
                command.append("--profile")
            r = json.loads(subprocess.run(command, check=True, capture_output=True, text=True).stdout)
            achieved = r["gflop"] / r["median_s"]
            print(
                f"| {name} | {size} | {r['median_s']:.3f} | {r['gflop']:.1f} | {achieved:.1f} | "
                f"{100 * achieved / rate:.0f} % | {r['peak_rss_mib']:.0f} | {r['rss_increase_mib']:.0f} |",
                flush=True,
            )
            if "profile" in r:
                profiles.append((f"{name} {size}", r["profile"]))
    for title, table in profiles:
        print(f"\n## profile: {title}\n{table}")


if __name__ == "__main__":
    main()
