"""The sequence benchmark's small version: a cold row and a warm row, as the full run prints them."""

import re
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "bench" / "sequence.py"


def test_the_benchmark_prints_time_accuracy_and_flicker_for_cold_and_warm_frames():
    command = [sys.executable, str(SCRIPT), "--frames", "3", "--size", "64x128", "--warm-iters", "2"]
    table = subprocess.run(command, check=True, capture_output=True, text=True, timeout=300).stdout
    number = r"([0-9.]+)"
    for mode in ("cold", "warm, 2 iters"):
        row = re.search(
            rf"^\| {mode} \| {number} \| {number}x \| {number} \| {number} \| {number} \|$", table, re.MULTILINE
        )
        assert row is not None, table
        milliseconds, _, epe, bad2, flicker = (float(value) for value in row.groups())
        assert milliseconds > 0 and epe > 0 and 0 <= bad2 <= 100 and flicker >= 0
    assert re.search(r"^\| cold \| [0-9]+ \| 1\.00x \|", table, re.MULTILINE), table
