"""evaluate(): joins predictions with ground truth per pair, averages per method, renders sheets."""

import json

import cv2
import numpy as np
import pytest

from crestereo_pp.evaluation.evaluate import SGBM, evaluate
from crestereo_pp.evaluation.metrics import sparsification
from crestereo_pp.evaluation.visualize import PANEL_WIDTH
from crestereo_pp.inference import InferenceOptions, Prediction
from crestereo_pp.inference.uncertainty_calibration import UncertaintyCalibration
from crestereo_pp.stereo_data.readers import StereoSample
from crestereo_pp.stereo_data.visualize import colorize


class OffsetPredictor:
    """Stands in for a StereoPredictor: predicts the true disparity plus `offset` px."""

    name = "lite"
    weights_sha256 = None
    num_parameters = 0
    calibration = None
    backend = "torch"
    precision = "fp32"

    def __init__(self, samples: list[StereoSample], offset: float) -> None:
        self.truth = {id(s.left): s.disparity for s in samples}
        self.offset = offset
        self.calls = 0
        self.two_pass = []

    def predict(self, left, right, *, two_pass="auto", **options):
        assert options.keys() <= InferenceOptions().keywords().keys()  # what StereoPredictor.predict takes
        self.calls += 1
        self.two_pass.append(two_pass)
        truth = self.truth[id(left)]
        disparity = np.where(np.isfinite(truth), truth + self.offset, 0.0).astype(np.float32)
        return Prediction(disparity, np.full(truth.shape, 0.25, np.float32))


def shifted_sample(name: str, disparity: int, seed: int, height: int = 48, width: int = 80) -> StereoSample:
    rng = np.random.default_rng(seed)
    texture = rng.integers(0, 256, (height, width + disparity, 3), dtype=np.uint8)
    truth = np.full((height, width), float(disparity), np.float32)
    truth[:, :disparity] = np.inf
    return StereoSample(name, texture[:, :width].copy(), texture[:, disparity:].copy(), truth, np.isfinite(truth))


@pytest.fixture
def samples() -> list[StereoSample]:
    return [shifted_sample("a", 3, 0), shifted_sample("b", 6, 1)]


def test_a_prediction_off_by_1_5_px_everywhere_scores_exactly_that(samples):
    report = evaluate(samples, OffsetPredictor(samples, 1.5), dataset_name="mem", progress=False)
    assert [p.name for p in report.pairs] == ["a", "b"] and report.method_names == ["lite"]
    for pair in report.pairs:
        m = pair.methods["lite"].metrics
        assert (m.epe, m.bad1, m.bad2, m.bad3, m.d1_all) == pytest.approx((1.5, 100.0, 0.0, 0.0, 0.0))
    assert report.pairs[0].methods["lite"].metrics.valid_pixels == 48 * (80 - 3)


def test_on_openvino_each_pair_is_predicted_once_untimed_before_its_timed_prediction_and_on_torch_not(samples):
    compiled = OffsetPredictor(samples, 0.0)
    compiled.backend = "openvino"
    evaluate(samples, compiled, dataset_name="mem", progress=False)
    assert compiled.calls == 2 * len(samples)
    assert compiled.two_pass == ["auto"] * 4  # the warm-up runs the pair's own way: the same options
    eager = OffsetPredictor(samples, 0.0)
    evaluate(samples, eager, dataset_name="mem", progress=False)
    assert eager.calls == len(samples)  # nothing to compile: every prediction is a timed one


def test_sgbm_rows_sit_beside_the_model_and_means_are_per_method(samples):
    report = evaluate(samples, OffsetPredictor(samples, 4.0), dataset_name="mem", baseline_sgbm=True, progress=False)
    assert report.method_names == ["lite", SGBM]
    assert report.mean("lite").metrics.epe == pytest.approx(4.0)
    sgbm_epes = [p.methods[SGBM].metrics.epe for p in report.pairs]
    assert report.mean(SGBM).metrics.epe == pytest.approx(np.mean(sgbm_epes))
    assert max(sgbm_epes) < 0.1  # an exact integer shift of random texture
    document = json.loads(json.dumps(report.to_dict()))
    assert document["mean"][SGBM]["metrics"]["epe"] == pytest.approx(np.mean(sgbm_epes))
    assert len(report.table().splitlines()) == 2 + 2 * 3  # header, rule, (2 pairs + mean) x 2 methods


def test_one_sheet_per_pair_with_a_row_per_method(samples, tmp_path):
    evaluate(
        samples,
        OffsetPredictor(samples, 0.0),
        dataset_name="mem",
        baseline_sgbm=True,
        sheets_dir=tmp_path,
        progress=False,
    )
    sheet = cv2.imread(str(tmp_path / "a.png"))
    assert sheet.shape[1] == 3 * PANEL_WIDTH
    panel_height = 24 + round(48 * PANEL_WIDTH / 80)
    plot_height = 24 + round(360 * PANEL_WIDTH / 720)
    assert sheet.shape[0] == 3 * panel_height + plot_height  # inputs, model, SGBM, sparsification


def test_a_pair_without_ground_truth_is_an_error():
    sample = shifted_sample("empty", 3, 0)
    sample = StereoSample(
        "empty", sample.left, sample.right, np.full((48, 80), np.inf, np.float32), np.zeros((48, 80), bool)
    )
    with pytest.raises(ValueError, match="no valid ground-truth pixel"):
        evaluate([sample], OffsetPredictor([sample], 0.0), dataset_name="mem", progress=False)


def test_color_scale_is_fixed_and_unknown_is_black():
    values = np.array([[0.0, 10.0, 20.0, np.inf]], np.float32)
    image = colorize(values, 0.0, 10.0)
    assert image.dtype == np.uint8 and image.shape == (1, 4, 3)
    np.testing.assert_array_equal(image[0, 1], image[0, 2])  # clipped at the top of the scale
    assert not np.array_equal(image[0, 0], image[0, 1])
    np.testing.assert_array_equal(image[0, 3], [0, 0, 0])


class HalfWrongPredictor(OffsetPredictor):
    """Off by 3 px on the left half of each image, exact on the right half, with a calibrated
    uncertainty that says so: `wrong_p` on the left half, 0.1 on the right."""

    calibration = UncertaintyCalibration(threshold_px=2.0, knots=(0.0, 1.0), probabilities=(0.0, 1.0), fitted_on="test")

    def __init__(self, samples: list[StereoSample], wrong_p: dict[str, float]) -> None:
        super().__init__(samples, 0.0)
        self.wrong_p = {id(s.left): wrong_p[s.name] for s in samples}

    def predict(self, left, right, **options):
        assert options.keys() <= InferenceOptions().keywords().keys()
        truth = self.truth[id(left)]
        half = truth.shape[1] // 2
        disparity = np.where(np.isfinite(truth), truth, 0.0).astype(np.float32)
        disparity[:, :half] += 3.0
        uncertainty = np.full(truth.shape, 0.1, np.float32)
        uncertainty[:, :half] = self.wrong_p[id(left)]
        return Prediction(disparity, uncertainty)


def test_the_pair_calibration_table_gives_each_pairs_observed_and_predicted_error_rates_and_ranking(samples):
    predictor = HalfWrongPredictor(samples, {"a": 0.5, "b": 0.9})
    report = evaluate(samples, predictor, dataset_name="mem", progress=False)
    lines = report.pair_calibration_table("lite").splitlines()
    rows = {line.split()[0]: [float(v) for v in line.split()[1:]] for line in lines[3:5]}
    for sample in samples:
        prediction = predictor.predict(sample.left, sample.right)
        errors = np.abs(prediction.disparity - sample.disparity)[sample.valid]
        trust = prediction.uncertainty[sample.valid]
        curve = sparsification(errors, trust)
        observed, predicted, ratio = rows[sample.name]
        assert observed == pytest.approx((errors > 2.0).mean(), abs=5e-4)
        assert predicted == pytest.approx(trust.mean(), abs=5e-4)
        assert ratio == pytest.approx(curve.auc / curve.auc_random, abs=5e-3)
        assert ratio < 1.0  # the wrong half is the flagged half
    mean_row = lines[5].split()
    assert mean_row[:3] == ["mean", "of", "2"]
    assert [float(v) for v in mean_row[4:]] == pytest.approx(
        np.mean(list(rows.values()), axis=0), abs=6e-3
    )  # of printed values
    # a: 0.5 on the wrong ~48 % of pixels and 0.1 elsewhere predicts ~0.29 (off by ~0.19); b predicts ~0.49
    assert lines[-1].startswith("pairs whose mean predicted is within 0.05 of the observed: 1 of 2")
    assert report.calibration_table().startswith(report.pair_calibration_table("lite"))
