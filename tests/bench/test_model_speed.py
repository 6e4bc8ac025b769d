"""The speed benchmark's small version: one torch row (two interleaved rounds) and the SGBM row, as the full
run prints them."""

import re
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "bench" / "model_speed.py"


def test_the_benchmark_prints_a_row_per_backend_and_precision_and_one_for_sgbm():
    command = [sys.executable, str(SCRIPT), "--models", "lite", "--sizes", "64x128", "--runs", "1", "--rounds", "2"]
    command += ["--backends", "torch", "--precisions", "fp32"]
    table = subprocess.run(command, check=True, capture_output=True, text=True, timeout=300).stdout
    row = re.search(r"^\| lite \| 64x128 \| torch \| fp32 \| ([0-9.]+) \| 1\.00x \| ([0-9.]+) \|", table, re.MULTILINE)
    assert row is not None, table
    assert float(row.group(1)) > 0 and float(row.group(2)) > 0  # latency (s) and GFLOP/s
    assert re.search(r"^\| SGBM \| 64x128 \| OpenCV \| - \| [0-9.]+ \|", table, re.MULTILINE), table
