"""`python -m crestereo_pp.evaluation.two_pass_rule`: the table that measures where two-pass inference pays."""

from pathlib import Path

import pytest

from crestereo_pp.evaluation.metrics import DisparityMetrics
from crestereo_pp.evaluation.two_pass_rule import PairRule, main, report, thresholds_between
from crestereo_pp.inference.two_pass import LARGE_DISPARITY_PX
from tests.shared_data import SMALL_STEREO_DEV_PAIR, STEREO_DEV


def metrics(bad2: float) -> DisparityMetrics:
    return DisparityMetrics(epe=1.0, bad1=2 * bad2, bad2=bad2, bad3=bad2 / 2, d1_all=bad2 / 2, valid_pixels=100)


def test_auto_takes_two_passes_above_the_threshold_enlarges_below_and_the_sweep_tries_every_split():
    size = (375, 1242)  # at most 1.5x within the pixel bound
    near = PairRule(
        "near", 40.0, size, one=metrics(10.0), two=metrics(12.0), enlarged={1.25: metrics(9.0), 1.5: metrics(8.0)}
    )
    middle = PairRule(
        "middle", 75.0, size, one=metrics(20.0), two=metrics(22.0), enlarged={1.25: metrics(19.0), 1.5: metrics(25.0)}
    )
    far = PairRule(
        "far", 120.0, size, one=metrics(30.0), two=metrics(20.0), enlarged={1.25: metrics(35.0), 1.5: metrics(40.0)}
    )
    rules = [far, near, middle]
    assert thresholds_between(rules) == [39.0, 57.5, 97.5, 121.0]
    assert [rule.way(97.5) for rule in (near, middle, far)] == [(False, 1.5), (False, 1.25), (True, 1.0)]
    assert (near.bad2(97.5), middle.bad2(97.5), far.bad2(97.5)) == (8.0, 19.0, 20.0)
    assert near.bad2(97.5, enlarge=False) == 10.0
    text = report(rules, threshold_px=97.5)
    assert "one pass 20.00, enlarged everywhere 1.25x 21.00, 1.5x 24.33, two passes 18.00" in text
    assert "auto at 97.5 px: 15.67" in text and "without enlarging 16.67" in text
    assert "39.0 px:  18.00 (3 pairs in two)" in text and "121.0 px:  19.00 (0 pairs in two)" in text


def test_on_a_real_near_pair_the_table_shows_its_evidence_and_auto_enlarges_it(tmp_path: Path, capsys):
    if not (STEREO_DEV / SMALL_STEREO_DEV_PAIR).is_dir():
        pytest.skip(f"real pairs not available: {STEREO_DEV} does not exist (see tests/shared_data.py)")
    (tmp_path / SMALL_STEREO_DEV_PAIR).symlink_to(STEREO_DEV / SMALL_STEREO_DEV_PAIR)
    assert main([str(tmp_path), "--backend", "torch", "--precision", "fp32"]) == 0
    table = capsys.readouterr().out
    (row,) = [line for line in table.splitlines() if line.startswith(SMALL_STEREO_DEV_PAIR)]
    name, evidence, picked, *_ = row.split()
    assert float(evidence) < LARGE_DISPARITY_PX and picked == "1.5x"
