"""The camera-shapes benchmark's small version: every scenario's row for one bound, on torch and
the smallest real pair, as the full run prints them on OpenVINO."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

from shared_data import SMALL_STEREO_DEV_PAIR, STEREO_DEV

SCRIPT = Path(__file__).resolve().parents[2] / "bench" / "camera_shapes.py"


def test_the_benchmark_prints_a_row_per_scenario_and_bound():
    if not STEREO_DEV.is_dir():
        pytest.skip(f"real pairs not available: {STEREO_DEV} does not exist (see tests/shared_data.py)")
    command = [sys.executable, str(SCRIPT), "--pair", SMALL_STEREO_DEV_PAIR, "--data", str(STEREO_DEV)]
    command += ["--calls", "1", "--compiled-mb", "768", "--backend", "torch"]
    table = subprocess.run(command, check=True, capture_output=True, text=True, timeout=300).stdout
    rows = re.findall(r"^\| ([^|]+) \| 768 \| ([0-9]+) \| ([0-9]+) \|$", table, re.MULTILINE)
    assert [row[0] for row in rows] == [
        "one pass, 1.25x",
        "one pass, 1.5x",
        "one pass, 1.25x and 1.5x in turn",
        "two passes, 1.5x",
        "one pass 1x and two passes 1.5x in turn",
    ], table
    assert all(int(median) == int(each) > 0 for _, median, each in rows)
