"""The mixed-load benchmark's small version: run as a user runs it (`python bench/mixed_load`) for a
few seconds against a real server with both models, it prints the memory table and the answers
table, finds no unexpected answer and writes its JSON record."""

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from service_helpers import run_uvicorn
from tests.shared_data import STEREO_DEV

REPO = Path(__file__).resolve().parents[2]
VERDICTS = {"ok", "expected", "shed"}  # and `unexpected`, which fails the run

pytestmark = pytest.mark.slow  # a real server and the benchmark's own processes


@pytest.mark.skipif(not STEREO_DEV.is_dir(), reason=f"no real stereo pairs at {STEREO_DEV}")
def test_a_short_mixed_load_prints_its_tables_and_records_every_sample_and_answer(tmp_path):
    record = tmp_path / "mixed.json"
    with run_uvicorn(tmp_path, models="lite,full") as server:
        command = [sys.executable, "bench/mixed_load", "--url", server.base_url, "--pid", str(server.process.pid)]
        command += ["--clients", "3", "--seconds", "10", "--sample-s", "1", "--variants", "4", "--calibrations", "1"]
        command += ["--data", str(STEREO_DEV), "--timeout-s", "60", "--json", str(record)]
        run = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=180)
        output = run.stdout + run.stderr
        assert run.returncode == 0, output + server.log()

    lines = run.stdout.splitlines()
    memory_header = "| t (s) | server RSS (MiB) | children RSS (MiB) | total (MiB) | /health/live (ms) |"
    assert memory_header in lines, output
    first_row = lines[lines.index(memory_header) + 2]
    assert re.fullmatch(r"\| 0 \| [0-9]+ \| [0-9]+ \| [0-9]+ \| [0-9]+ \|", first_row), output
    peak = r"^peak server RSS [0-9]+ MiB at [0-9]+ s; /health/live max [0-9]+ ms, failed 0$"
    assert re.search(peak, run.stdout, re.MULTILINE), output
    assert "| job | status | code | verdict | count |" in lines, output
    assert "| unexpected |" not in run.stdout, output
    totals = r"^([0-9]+) answers: ok ([0-9]+), expected [0-9]+, shed [0-9]+, unexpected 0(; ok latency .*)?$"
    summary = re.search(totals, run.stdout, re.MULTILINE)
    assert summary is not None, output
    answers, ok = int(summary.group(1)), int(summary.group(2))
    assert ok > 0, output

    saved = json.loads(record.read_text())
    assert saved["args"]["pid"] == str(server.process.pid) and saved["args"]["clients"] == "3"
    samples, outcomes = saved["samples"], saved["outcomes"]
    assert len(samples) >= 8 and all(s["server_mib"] > 0 and s["live_ms"] is not None for s in samples)
    assert set(samples[0]) == {"t", "server_mib", "children_mib", "children", "live_ms", "answers"}
    assert samples[-1]["answers"] == answers == len(outcomes)
    assert {o["verdict"] for o in outcomes} <= VERDICTS
    assert all(set(o) == {"job", "status", "code", "verdict", "seconds"} for o in outcomes)
