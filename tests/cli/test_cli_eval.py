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
from crestereo_pp.evaluation.metrics import compute_metrics
from crestereo_pp.evaluation.sgbm import sgbm_disparity
from crestereo_pp.model import CREStereoPP, ModelConfig
from crestereo_pp.stereo_data.synthetic import SceneConfig, SceneGenerator

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


def test_eval_runs_and_records_the_inference_knobs(pairs_dir, tmp_path, capsys):
    out = tmp_path / "report.json"
    argv = ["eval", str(pairs_dir), "--device", "cpu", "--iters", "1", "1", "2", "--scale", "0.5", "--flip"]
    assert main([*argv, "--json", str(out)]) == 0
    model = json.loads(out.read_text())["model"]
    assert (model["iters"], model["scale"], model["two_pass"], model["flip"]) == ([1, 1, 2], 0.5, "auto", True)
    capsys.readouterr()
    assert main(["eval", str(pairs_dir), "--device", "cpu", "--iters", "1", "2"]) == 2  # a usage error
    assert "1 or 3 counts" in capsys.readouterr().err


def test_eval_on_procedural_scenes_of_one_kind_scores_them_against_their_exact_ground_truth(tmp_path):
    out = tmp_path / "report.json"
    argv = ["eval", "--procedural", "--scene", "thin_probability=1", "--scene", "max_disparity=24"]
    argv += ["--scenes", "2", "--size", "64x128", "--seed", "5", "--baseline", "sgbm", "--json", str(out)]
    assert main([*argv, "--device", "cpu", "--iters", "1", "1", "1"]) == 0

    report = json.loads(out.read_text())
    assert report["dataset"] == "2 procedural scenes 64x128 thin_probability=1 max_disparity=24, seeds from 5"
    scenes = SceneGenerator(SceneConfig(height=64, width=128, thin_probability=1.0, max_disparity=24.0)).samples(2, 5)
    assert [pair["name"] for pair in report["pairs"]] == [scene.name for scene in scenes]
    for pair, scene in zip(report["pairs"], scenes, strict=True):
        known = scene.valid
        sgbm = pair["methods"]["sgbm"]["metrics"]
        expected = compute_metrics(
            sgbm_disparity(scene.left, scene.right, float(scene.disparity.max()))[0], scene.disparity, known
        )
        assert sgbm["valid_pixels"] == 64 * 128 and sgbm["epe"] == pytest.approx(expected.epe)


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["--procedural", "--scene", "nope=1"], "numeric scene settings: "),
        (["--procedural", "--scene", "height=64"], "numeric scene settings: "),  # the size is --size's
        (["--procedural", "--scene", "thin_probability=lots"], "thin_probability takes a number"),
        (["--procedural", "--size", "64by128"], "expected HEIGHTxWIDTH"),
        (["--procedural", "--scenes", "0"], "expected a positive whole number"),
    ],
)
def test_eval_refuses_procedural_settings_it_cannot_use_and_says_why(argv, says, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["eval", *argv])
    assert exit_.value.code == 2 and says in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["--procedural", "somewhere"], "give either DATA_DIR or --procedural"),
        ([], "give either DATA_DIR or --procedural"),
        (["somewhere", "--scene", "thin_probability=1"], "--scene sets procedural scenes"),
        (["--procedural", "--scene", "thin_probability=2"], "thin_probability"),
    ],
)
def test_eval_needs_real_pairs_or_procedural_scenes_and_scene_values_the_generator_takes(argv, says, capsys):
    assert main(["eval", *argv]) == 2
    assert says in capsys.readouterr().err
