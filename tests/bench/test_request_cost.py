"""The request-cost benchmark's small version: a row per request, its modelled cost the service's own."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.shared_data import STEREO_DEV

SCRIPT = Path(__file__).resolve().parents[2] / "bench" / "request_cost.py"


@pytest.mark.skipif(not STEREO_DEV.is_dir(), reason=f"no real stereo pairs at {STEREO_DEV}")
def test_the_benchmark_prints_each_requests_modelled_and_measured_cost_against_a_plain_request():
    command = [sys.executable, str(SCRIPT), "--data", str(STEREO_DEV), "--sizes", "64x96", "--runs", "1"]
    command += ["--requests", "flip,scale-0.5", "--backend", "torch"]
    table = subprocess.run(command, check=True, capture_output=True, text=True, timeout=300).stdout
    number = r"([0-9.]+)"
    rows = {
        name: re.search(
            rf"^\| 64x96 \| {name} \| {number} \| {number} \| {number} \| {number} \|$", table, re.MULTILINE
        )
        for name in ("plain", "flip", "scale-0.5")
    }
    assert all(rows.values()), table
    modelled = {name: float(row.group(1)) for name, row in rows.items() if row}
    # the service's own model, to the two decimals printed: flip all of it twice; scale 0.5 the
    # network's quarter of the pixels and the share of the time that stays at the pair's size
    assert modelled == pytest.approx({"plain": 1.0, "flip": 2.0, "scale-0.5": 0.3 + 0.7 * 0.25}, abs=0.006)
    plain = rows["plain"]
    assert plain is not None and float(plain.group(3)) == 1.0 and float(plain.group(2)) > 0
    for row in rows.values():
        assert row is not None and float(row.group(4)) == pytest.approx(
            float(row.group(3)) / float(row.group(1)), abs=0.03
        )


def test_an_unknown_request_is_refused_naming_the_requests():
    command = [sys.executable, str(SCRIPT), "--requests", "flipped"]
    run = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert run.returncode != 0 and "unknown request 'flipped'; the requests are plain, auto" in run.stderr
