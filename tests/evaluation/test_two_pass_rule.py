"""`python -m crestereo_pp.evaluation.two_pass_rule`: the table that measures where two-pass inference pays."""

from pathlib import Path

import pytest

from crestereo_pp.evaluation.metrics import DisparityMetrics
from crestereo_pp.evaluation.two_pass_rule import PairRule, main, report, thresholds_between
from crestereo_pp.inference.two_pass import LARGE_DISPARITY_PX
from tests.shared_data import SMALL_STEREO_DEV_PAIR, STEREO_DEV


def metrics(bad2: float) -> DisparityMetrics:
    return DisparityMetrics(epe=1.0, bad1=2 * bad2, bad2=bad2, bad3=bad2 / 2, d1_all=bad2 / 2, valid_pixels=100)


def test_auto_takes_two_passes_above_the_threshold_and_the_sweep_tries_every_split_of_the_pairs():
    near = PairRule("near", 40.0, one=metrics(10.0), two=metrics(12.0))
    far = PairRule("far", 120.0, one=metrics(30.0), two=metrics(20.0))
    assert thresholds_between([far, near]) == [39.0, 80.0, 121.0]
    assert (near.bad2(80.0), far.bad2(80.0)) == (10.0, 20.0)
    text = report([near, far], threshold_px=80.0)
    assert "one pass 20.00, two passes 16.00, auto at 80 px 15.00" in text
    assert "39.0 px:  16.00 (2 pairs in two)" in text and "121.0 px:  20.00 (0 pairs in two)" in text


def test_on_a_real_near_pair_the_table_shows_its_evidence_and_auto_keeps_one_pass(tmp_path: Path, capsys):
    if not (STEREO_DEV / SMALL_STEREO_DEV_PAIR).is_dir():
        pytest.skip(f"real pairs not available: {STEREO_DEV} does not exist (see tests/shared_data.py)")
    (tmp_path / SMALL_STEREO_DEV_PAIR).symlink_to(STEREO_DEV / SMALL_STEREO_DEV_PAIR)
    assert main([str(tmp_path), "--backend", "torch", "--precision", "fp32"]) == 0
    table = capsys.readouterr().out
    (row,) = [line for line in table.splitlines() if line.startswith(SMALL_STEREO_DEV_PAIR)]
    name, evidence, picked, *_ = row.split()
    assert float(evidence) < LARGE_DISPARITY_PX and picked == "one"
