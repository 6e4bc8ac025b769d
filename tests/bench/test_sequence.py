"""The sequence benchmark's small version: the drift table and the summary, as the full run prints them."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.shared_data import STEREO_DEV

SCRIPT = Path(__file__).resolve().parents[2] / "bench" / "sequence.py"


@pytest.mark.skipif(not STEREO_DEV.is_dir(), reason=f"no real stereo pairs at {STEREO_DEV}")
def test_the_benchmark_prints_each_frames_drift_and_the_time_of_warm_and_cold_frames():
    command = [sys.executable, str(SCRIPT), "--data", str(STEREO_DEV), "--frames", "2", "--size", "64x96"]
    table = subprocess.run(command + ["--warm-iters", "2"], check=True, capture_output=True, text=True, timeout=300)
    lines = table.stdout.splitlines()
    assert "| frame | static, warm 2 | pan 1,1, warm 2 |" in lines, table.stdout
    number = r"([0-9.]+)"
    for frame in (1, 2):
        row = re.search(rf"^\| {frame} \| {number} \| {number} \|$", table.stdout, re.MULTILINE)
        assert row is not None, table.stdout
        assert all(float(drift) >= 0 for drift in row.groups())
    drifts = rf"{number} mean, {number} worst"
    summary = re.search(
        rf"^\| 2 \| {number} \| {number} \| {number}x \| {drifts} \| {drifts} \|$", table.stdout, re.MULTILINE
    )
    assert summary is not None, table.stdout
    warm_ms, cold_ms, _, static_mean, static_worst, pan_mean, pan_worst = (float(v) for v in summary.groups())
    assert warm_ms > 0 and cold_ms > 0 and static_mean <= static_worst and pan_mean <= pan_worst
