"""`python -m crestereo_pp.evaluation.two_pass_rule`: the table that measures where two-pass inference pays."""

from pathlib import Path

import pytest

from crestereo_pp.evaluation.metrics import DisparityMetrics
from crestereo_pp.evaluation.two_pass_rule import WAYS, PairRule, main, report, thresholds_between
from crestereo_pp.inference.two_pass import LARGE_DISPARITY_PX
from tests.shared_data import SMALL_STEREO_DEV_PAIR, STEREO_DEV


def metrics(bad2: float) -> DisparityMetrics:
    return DisparityMetrics(epe=1.0, bad1=2 * bad2, bad2=bad2, bad3=bad2 / 2, d1_all=bad2 / 2, valid_pixels=100)


def rule(name: str, evidence_px: float, bad2: dict[tuple[bool, float], float]) -> PairRule:
    """A 375 x 1242 pair (at most 1.5x within the pixel bound) with these bad-2 per way, 50 % in
    the other ways (which only the sweep's lowest thresholds take)."""
    return PairRule(name, evidence_px, (375, 1242), {way: metrics(bad2.get(way, 50.0)) for way in WAYS})


def test_auto_takes_the_way_of_its_evidence_and_the_sweep_tries_every_split():
    near = rule("near", 40.0, {(False, 1.0): 10.0, (False, 1.25): 9.0, (False, 1.5): 8.0, (True, 1.0): 12.0})
    middle = rule("middle", 75.0, {(False, 1.0): 20.0, (False, 1.25): 19.0, (False, 1.5): 25.0, (True, 1.0): 22.0})
    far = rule("far", 130.0, {(False, 1.0): 30.0, (True, 1.0): 20.0, (True, 1.25): 18.0, (True, 1.5): 40.0})
    rules = [far, near, middle]
    assert thresholds_between(rules) == [39.0, 57.5, 102.5, 131.0]
    # one pass: enlarged while evidence x factor <= 100; two: while half of it x factor <= 90
    assert [r.way(102.5) for r in (near, middle, far)] == [(False, 1.5), (False, 1.25), (True, 1.25)]
    assert (near.bad2(102.5), middle.bad2(102.5), far.bad2(102.5)) == (8.0, 19.0, 18.0)
    assert (near.bad2(102.5, resize=False), far.bad2(102.5, resize=False)) == (10.0, 20.0)
    text = report(rules, threshold_px=102.5)
    assert "each way everywhere: one 1x 20.00, one 1.25x 26.00, one 1.5x 27.67, two 1x 18.00" in text
    assert "auto at 102.5 px: bad-2 15.00" in text and "without resizing: bad-2 16.67" in text
    assert "131.0 px:  19.00 (0 pairs in two)" in text


def test_on_a_real_near_pair_the_table_shows_its_evidence_and_auto_enlarges_it(tmp_path: Path, capsys):
    if not (STEREO_DEV / SMALL_STEREO_DEV_PAIR).is_dir():
        pytest.skip(f"real pairs not available: {STEREO_DEV} does not exist (see tests/shared_data.py)")
    (tmp_path / SMALL_STEREO_DEV_PAIR).symlink_to(STEREO_DEV / SMALL_STEREO_DEV_PAIR)
    assert main([str(tmp_path), "--backend", "torch", "--precision", "fp32"]) == 0
    table = capsys.readouterr().out
    (row,) = [line for line in table.splitlines() if line.startswith(SMALL_STEREO_DEV_PAIR)]
    name, evidence, passes, factor, *_ = row.split()
    assert float(evidence) < LARGE_DISPARITY_PX and (passes, factor) == ("one", "1.5x")
