"""Evaluate a predictor (and optionally the SGBM baseline) on a dataset of pairs with ground truth."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from crestereo_pp.inference import InferenceOptions, Prediction, StereoPredictor
from crestereo_pp.stereo_data.formats import encode_png
from crestereo_pp.stereo_data.readers import StereoSample

from .metrics import (
    DisparityMetrics,
    Reliability,
    Sparsification,
    compute_metrics,
    mean_metrics,
    mean_sparsification,
    pool_reliability,
    reliability,
    sparsification,
)
from .sgbm import sgbm_disparity
from .visualize import evaluation_sheet

SGBM = "sgbm"
"""Method name of the OpenCV StereoSGBM baseline in reports."""
CALIBRATION_TOLERANCE = 0.05
"""How far a pair's mean predicted probability of a large error may be from its observed share of
large errors for `pair_calibration_table` to count the pair as calibrated."""


@dataclass(frozen=True)
class MethodResult:
    """One method on one pair: its metrics, the seconds one prediction took, and how well its
    uncertainty ranks its errors (bad-2 sparsification)."""

    metrics: DisparityMetrics
    seconds: float
    sparsification: Sparsification
    reliability: Reliability | None = None  # when the uncertainty is a calibrated probability


@dataclass(frozen=True)
class PairResult:
    """All methods on one pair (`methods` maps method name -> result, in evaluation order)."""

    name: str
    width: int
    height: int
    methods: dict[str, MethodResult]


@dataclass(frozen=True)
class EvaluationReport:
    """Per-pair results of every method, plus what identifies the model."""

    dataset: str
    model: dict[str, Any]
    pairs: list[PairResult] = field(default_factory=list)

    @property
    def method_names(self) -> list[str]:
        return list(self.pairs[0].methods) if self.pairs else []

    def mean(self, method: str) -> MethodResult:
        """Unweighted mean over pairs of the metrics, the time and the sparsification of `method`."""
        results = [pair.methods[method] for pair in self.pairs]
        reliabilities = [r.reliability for r in results if r.reliability is not None]
        return MethodResult(
            mean_metrics([r.metrics for r in results]),
            float(np.mean([r.seconds for r in results])),
            mean_sparsification([r.sparsification for r in results]),
            pool_reliability(reliabilities) if len(reliabilities) == len(results) else None,
        )

    def to_dict(self) -> dict[str, Any]:
        """Every number of the report, JSON-ready."""
        return {
            "dataset": self.dataset,
            "model": self.model,
            "pairs": [asdict(pair) for pair in self.pairs],
            "mean": {method: asdict(self.mean(method)) for method in self.method_names},
        }

    def table(self) -> str:
        """Plain-text table: one row per pair and method, then one mean row per method."""
        header = (
            f"{'pair':<34} {'method':<6} {'EPE':>7} {'bad-1%':>7} {'bad-2%':>7} {'bad-3%':>7}"
            f" {'D1-all%':>8} {'time s':>8}"
        )

        def row(result: MethodResult) -> str:
            m = result.metrics
            return f"{m.epe:>7.3f} {m.bad1:>7.2f} {m.bad2:>7.2f} {m.bad3:>7.2f} {m.d1_all:>8.2f} {result.seconds:>8.3f}"

        return self._rows(header, row)

    def _rows(self, header: str, row: Callable[[MethodResult], str]) -> str:
        """A plain-text table: `header`, then per pair and method (then per method, the mean
        over pairs) the pair, the method and `row` of its result."""
        lines = [header, "-" * len(header)]
        groups = [(pair.name, pair.methods) for pair in self.pairs]
        groups.append((f"mean of {len(self.pairs)} pairs", {m: self.mean(m) for m in self.method_names}))
        for label, methods in groups:
            for method, result in methods.items():
                lines.append(f"{label:<34.34} {method:<6} {row(result)}")
                label = ""
        return "\n".join(lines)

    def calibration_table(self) -> str:
        """Plain-text reliability table (all pixels of all pairs) of each method whose
        uncertainty is a calibrated probability, then its per-pair table
        (`pair_calibration_table`); empty when there is none."""
        blocks = []
        for method in self.method_names:
            pooled = self.mean(method).reliability
            if pooled is None:
                continue
            blocks.append(self.pair_calibration_table(method))
            lines = [
                f"{method}: predicted vs observed P(error > {pooled.threshold_px:g} px), all pixels of "
                f"{len(self.pairs)} pairs; expected calibration error {pooled.expected_calibration_error:.4f}",
                f"{'bin':<9} {'predicted':>9} {'observed':>9} {'pixels':>10}",
            ]
            bins = len(pooled.pixels)
            for index, (predicted, observed, pixels) in enumerate(
                zip(pooled.predicted, pooled.observed, pooled.pixels, strict=True)
            ):
                lines.append(
                    f"{index / bins:.1f}-{(index + 1) / bins:.1f}   {predicted:>9.3f} {observed:>9.3f} {pixels:>10}"
                )
            blocks.append("\n".join(lines))
        return "\n\n".join(blocks)

    def pair_calibration_table(self, method: str, tolerance: float = CALIBRATION_TOLERANCE) -> str:
        """Plain-text table of `method`'s calibrated uncertainty pair by pair: the observed share
        of pixels wrong by over the threshold, the mean predicted probability, and the
        sparsification AUC / random AUC (below 1: the map ranks the errors better than chance);
        then the means over pairs (each pair counts once; AUC / random is the mean of the pairs'
        ratios) and how many pairs have their mean predicted within `tolerance` of the observed."""
        header = f"{'pair':<34} {'observed':>8} {'predicted':>9} {'AUC/rnd':>8}"
        rows = []
        for pair in self.pairs:
            result = pair.methods[method]
            assert result.reliability is not None, f"{method} has no calibrated uncertainty on {pair.name}"
            rows.append(
                (
                    pair.name,
                    result.reliability.observed_rate,
                    result.reliability.mean_predicted,
                    result.sparsification.ratio_to_random,
                )
            )
        threshold = self.pairs[0].methods[method].sparsification.threshold_px
        close = sum(abs(predicted - observed) <= tolerance for _, observed, predicted, _ in rows)
        means = [float(np.nanmean([row[i] for row in rows])) for i in (1, 2, 3)]
        lines = [
            f"{method}: observed vs mean predicted P(error > {threshold:g} px) and AUC / random, pair by pair",
            header,
            "-" * len(header),
            *(f"{name:<34.34} {obs:>8.3f} {pred:>9.3f} {ratio:>8.2f}" for name, obs, pred, ratio in rows),
            f"{f'mean of {len(rows)} pairs':<34} {means[0]:>8.3f} {means[1]:>9.3f} {means[2]:>8.2f}",
            f"pairs whose mean predicted is within {tolerance:g} of the observed: {close} of {len(rows)}; "
            f"worst AUC / random {float(np.nanmax([row[3] for row in rows])):.2f}",
        ]
        return "\n".join(lines)

    def uncertainty_table(self) -> str:
        """Plain-text table of how each method's uncertainty ranks its errors: bad-2 after
        removing the most uncertain 0/25/50/75 % of pixels, AUC, optimal AUC, random AUC and
        AUC / optimal (1 = perfect ranking; random / optimal = no ranking at all)."""
        header = (
            f"{'pair':<34} {'method':<6} {'bad2@0%':>8} {'@25%':>6} {'@50%':>6} {'@75%':>6}"
            f" {'AUC':>7} {'AUCopt':>7} {'AUCrnd':>7} {'AUC/opt':>8}"
        )

        def row(result: MethodResult) -> str:
            sp = result.sparsification
            at = dict(zip(sp.removed_percent, sp.bad_percent, strict=True))
            return (
                f"{at[0.0]:>8.2f} {at[25.0]:>6.2f} {at[50.0]:>6.2f} {at[75.0]:>6.2f}"
                f" {sp.auc:>7.4f} {sp.auc_optimal:>7.4f} {sp.auc_random:>7.4f} {sp.ratio_to_optimal:>8.2f}"
            )

        return self._rows(header, row)


def evaluate(
    dataset: Sequence[StereoSample],
    predictor: StereoPredictor,
    *,
    dataset_name: str,
    baseline_sgbm: bool = False,
    sheets_dir: Path | None = None,
    options: InferenceOptions | None = None,
    progress: bool = True,
) -> EvaluationReport:
    """Predict every pair of `dataset` with `predictor` (and SGBM when `baseline_sgbm`), score it.

    options: how each pair is computed (`StereoPredictor.predict`'s options; None: the defaults).
    Times are wall-clock seconds of one prediction; on OpenVINO after the same prediction untimed
    (which compiles the shapes the pair runs at, or brings them back into memory: with two_pass
    "auto" pairs of one size may run at different shapes, more than the compiled-shape bound
    keeps), as a camera's next frame would run. The progress bar shows the model's seconds of the
    last pair beside its own rate, which also counts reading, scoring, SGBM and those warm-ups.
    With `sheets_dir`, writes `sheets_dir/NAME.png` per pair: left image, ground truth,
    uncertainty, then each method's disparity and error map, on fixed colour scales (disparity
    0..max ground truth of the pair; error 0..ERROR_SCALE_PX).
    """
    if len(dataset) == 0:
        raise ValueError(f"{dataset_name} holds no stereo pairs")
    options = options or InferenceOptions()
    report = EvaluationReport(
        dataset=dataset_name,
        model={
            "name": predictor.name,
            "weights_sha256": predictor.weights_sha256,
            "num_parameters": predictor.num_parameters,
            "backend": predictor.backend,
            "precision": predictor.precision,
            "iters": options.iters,  # None: the model's own
            "two_pass": options.two_pass,
            "scale": options.scale,
            "flip": options.flip,
            "blend_sgbm": options.blend_sgbm,
            "refine_edges": options.refine_edges,
            "align_rows": options.align_rows,
            "uncertainty": (
                f"P(error > {predictor.calibration.threshold_px:g} px), fitted on {predictor.calibration.fitted_on}"
                if predictor.calibration is not None
                else "the paper's U of the last iteration (no calibration in the weights)"
            ),
        },
    )

    def predict(sample: StereoSample) -> Prediction:
        return predictor.predict(sample.left, sample.right, **options.keywords())

    bar = tqdm(range(len(dataset)), desc=f"eval {predictor.name}", unit="pair", disable=not progress)
    for index in bar:
        sample = dataset[index]
        known = sample.valid & np.isfinite(sample.disparity)
        if not known.any():
            raise ValueError(f"pair {sample.name!r} has no valid ground-truth pixel")
        if predictor.backend == "openvino":  # compiles (or reloads) the shapes this pair's way runs at
            predict(sample)
        start = time.perf_counter()
        prediction = predict(sample)
        seconds = time.perf_counter() - start
        bar.set_postfix_str(f"{predictor.name} {seconds:.2f} s")
        outputs = {predictor.name: (prediction.disparity, prediction.uncertainty, seconds)}
        calibration = predictor.calibration
        if baseline_sgbm:
            start = time.perf_counter()
            baseline = sgbm_disparity(sample.left, sample.right, float(sample.disparity[known].max()))
            outputs[SGBM] = (*baseline, time.perf_counter() - start)
        methods = {}
        for name, (disparity, uncertainty, seconds) in outputs.items():
            errors, trust = np.abs(disparity - sample.disparity)[known], uncertainty[known]
            calibrated = calibration if name == predictor.name else None
            methods[name] = MethodResult(
                compute_metrics(disparity, sample.disparity, known),
                seconds,
                sparsification(errors, trust),
                reliability(errors, trust, calibrated.threshold_px) if calibrated is not None else None,
            )
        height, width = sample.disparity.shape
        report.pairs.append(PairResult(sample.name, width, height, methods))
        if sheets_dir is not None:
            disparities = {name: disparity for name, (disparity, _, _) in outputs.items()}
            curves = {name: result.sparsification for name, result in methods.items()}
            sheet = evaluation_sheet(sample, known, prediction.uncertainty, disparities, curves)
            sheets_dir.mkdir(parents=True, exist_ok=True)
            (sheets_dir / f"{sample.name}.png").write_bytes(encode_png(sheet))
    return report
