"""`crestereo-pp eval`: table, JSON, sheets, SGBM rows; on generated pairs and on a real pair."""

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import cv2
import pytest
import torch

from crestereo_pp.cli.main import main
from crestereo_pp.model import CREStereoPP, ModelConfig

REPO = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.filterwarnings("ignore:no weights at:RuntimeWarning")


def test_eval_prints_per_pair_and_mean_rows_and_writes_json_and_sheets(pairs_dir, tmp_path, capsys):
    out, sheets = tmp_path / "report.json", tmp_path / "sheets"

    status = main(
        [
            "eval",
            str(pairs_dir),
            "--model",
            "lite",
            "--device",
            "cpu",
            "--baseline",
            "sgbm",
            "--json",
            str(out),
            "--sheets",
            str(sheets),
        ]
    )

    assert status == 0
    table = capsys.readouterr().out
    for text in (
        "EPE",
        "bad-1%",
        "bad-2%",
        "bad-3%",
        "D1-all%",
        "time s",
        "shift4",
        "shift9",
        "mean of 2 pairs",
        "sgbm",
    ):
        assert text in table
    report = json.loads(out.read_text())
    assert [p["name"] for p in report["pairs"]] == ["shift4", "shift9"]
    assert set(report["mean"]) == {"lite", "sgbm"}
    first = report["pairs"][0]["methods"]["sgbm"]
    assert set(first["metrics"]) == {"epe", "bad1", "bad2", "bad3", "d1_all", "valid_pixels"} and first["seconds"] > 0
    assert first["metrics"]["valid_pixels"] == 64 * (96 - 4)  # the unknown band of 4 columns does not count
    # SGBM finds a constant shift on a textured pair almost exactly
    assert report["mean"]["sgbm"]["metrics"]["bad1"] < 2.0
    assert report["model"]["name"] == "lite" and report["model"]["num_parameters"] > 0
    sheet = cv2.imread(str(sheets / "shift4.png"))
    assert sheet is not None and sheet.shape[1] == 3 * 480 and sheet.shape[0] > 3 * 24  # 3 rows of panels


def test_eval_reports_the_sha256_of_the_weights_it_loaded(pairs_dir, tmp_path):
    weights = tmp_path / "lite.pt"
    config = ModelConfig.preset("lite")
    torch.save({"model": CREStereoPP(config).state_dict(), "config": config.to_dict()}, weights)
    out = tmp_path / "report.json"

    assert main(["eval", str(pairs_dir), "--weights", str(weights), "--limit", "1", "--json", str(out)]) == 0

    report = json.loads(out.read_text())
    assert report["model"]["weights_sha256"] == hashlib.sha256(weights.read_bytes()).hexdigest()
    assert len(report["pairs"]) == 1 and set(report["mean"]) == {"lite"}


@pytest.mark.slow
def test_eval_of_a_folder_without_pairs_fails_with_a_clear_message(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "crestereo_pp.cli.main", "eval", str(tmp_path)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2
    assert "no known stereo dataset layout" in result.stderr and "Traceback" not in result.stderr


def test_sgbm_rows_on_a_real_pair_match_the_stereo_dev_readme(small_stereo_dev, tmp_path):
    out = tmp_path / "report.json"
    assert main(["eval", str(small_stereo_dev), "--baseline", "sgbm", "--json", str(out), "--device", "cpu"]) == 0
    (pair,) = json.loads(out.read_text())["pairs"]
    sgbm = pair["methods"]["sgbm"]["metrics"]
    readme = json.loads((small_stereo_dev / pair["name"] / "meta.json").read_text())["opencv_sgbm"]
    assert sgbm["epe"] == pytest.approx(readme["epe"], abs=0.001)
    assert (sgbm["bad1"], sgbm["bad2"], sgbm["bad3"]) == pytest.approx(
        (readme["bad1_pct"], readme["bad2_pct"], readme["bad3_pct"]), abs=0.01
    )


def test_eval_runs_and_records_the_inference_knobs(pairs_dir, tmp_path):
    out = tmp_path / "report.json"
    argv = ["eval", str(pairs_dir), "--device", "cpu", "--iters", "1", "1", "2", "--scale", "0.5"]
    assert main([*argv, "--json", str(out)]) == 0
    model = json.loads(out.read_text())["model"]
    assert (model["iters"], model["scale"], model["two_pass"]) == ([1, 1, 2], 0.5, "auto")
    with pytest.raises(SystemExit, match="1 or 3 counts"):
        main(["eval", str(pairs_dir), "--device", "cpu", "--iters", "1", "2"])
