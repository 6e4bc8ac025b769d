"""Where two-pass inference pays, pair by pair: the evidence ``two_pass="auto"`` decides by (the
99th percentile of a quick quarter-resolution pass's disparity) beside bad-2 and EPE of one pass and
of two passes, what auto picks, and the mean bad-2 that each threshold between the pairs'
evidence would give. How ``inference.two_pass.LARGE_DISPARITY_PX`` is measured for new weights:

    python -m crestereo_pp.evaluation.two_pass_rule ../shared/data/stereo-dev [--model lite] [--weights W]
                                       [--backend auto] [--precision auto]
"""

from __future__ import annotations

import argparse
import statistics
import sys
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from crestereo_pp.evaluation.metrics import DisparityMetrics, compute_metrics
from crestereo_pp.inference import StereoPredictor, load_model
from crestereo_pp.inference.prediction import as_image_batch
from crestereo_pp.inference.two_pass import LARGE_DISPARITY_PX
from crestereo_pp.stereo_data.readers import StereoSample, open_dataset


@dataclass(frozen=True)
class PairRule:
    """One pair: the auto rule's evidence (px) and the metrics of one and of two passes."""

    name: str
    evidence_px: float
    one: DisparityMetrics
    two: DisparityMetrics

    def picks_two(self, threshold_px: float) -> bool:
        return self.evidence_px > threshold_px

    def bad2(self, threshold_px: float) -> float:
        return (self.two if self.picks_two(threshold_px) else self.one).bad2


def measure(samples: Sequence[StereoSample], predictor: StereoPredictor) -> list[PairRule]:
    """Each pair computed in one pass and in two, with the evidence the auto rule reads."""
    rules = []
    for sample in samples:
        known = sample.valid & np.isfinite(sample.disparity)
        evidence = predictor.large_disparity_percentile(
            as_image_batch(sample.left, predictor.device), as_image_batch(sample.right, predictor.device)
        )
        one, two = (predictor.predict(sample.left, sample.right, two_pass=flag).disparity for flag in (False, True))
        rules.append(
            PairRule(
                sample.name,
                float(evidence[0]),
                compute_metrics(one, sample.disparity, known),
                compute_metrics(two, sample.disparity, known),
            )
        )
    return rules


def thresholds_between(rules: Sequence[PairRule]) -> list[float]:
    """Candidate thresholds: below every pair's evidence, between each two neighbours, above all."""
    evidence = sorted(rule.evidence_px for rule in rules)
    middles = [(low + high) / 2 for low, high in zip(evidence, evidence[1:], strict=False)]
    return [evidence[0] - 1.0, *middles, evidence[-1] + 1.0]


def report(rules: Sequence[PairRule], threshold_px: float = LARGE_DISPARITY_PX) -> str:
    """The per-pair table, its means, and the threshold sweep, as text."""
    lines = [
        f"{'pair':34} {'p99 px':>7} {'auto':>5} {'bad-2 one':>9} {'two':>6} {'EPE one':>8} {'two':>6}",
        "-" * 82,
    ]
    for rule in rules:
        lines.append(
            f"{rule.name[:34]:34} {rule.evidence_px:7.1f} {'two' if rule.picks_two(threshold_px) else 'one':>5} "
            f"{rule.one.bad2:9.2f} {rule.two.bad2:6.2f} {rule.one.epe:8.3f} {rule.two.epe:6.3f}"
        )

    def mean(values: Sequence[float]) -> float:
        return statistics.fmean(values)

    one, two = mean([r.one.bad2 for r in rules]), mean([r.two.bad2 for r in rules])
    lines += [
        "",
        f"mean bad-2: one pass {one:.2f}, two passes {two:.2f}, "
        f"auto at {threshold_px:g} px {mean([r.bad2(threshold_px) for r in rules]):.2f}",
        "mean bad-2 by threshold (two passes where p99 > threshold):",
    ]
    for threshold in thresholds_between(rules):
        picked = sum(rule.picks_two(threshold) for rule in rules)
        lines.append(f"  {threshold:7.1f} px: {mean([r.bad2(threshold) for r in rules]):6.2f} ({picked} pairs in two)")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], prog="python -m crestereo_pp.evaluation.two_pass_rule"
    )
    parser.add_argument("dataset", help="a folder of stereo pairs with ground truth")
    parser.add_argument("--model", default="lite", help="network [lite]")
    parser.add_argument("--weights", help="weights file [the bundled ones]")
    parser.add_argument("--backend", default="auto", choices=["auto", "torch", "openvino"], help="[auto]")
    parser.add_argument("--precision", default="auto", choices=["auto", "fp32", "bf16"], help="[auto]")
    args = parser.parse_args(argv)
    dataset = open_dataset(args.dataset)
    predictor = load_model(args.model, args.weights, backend=args.backend, precision=args.precision)
    if not (predictor.ready() and predictor.ready(warm_start=True)):  # one pass, and two (the second starts warm)
        print("exporting OpenVINO's graphs, once per weights (minutes; `crestereo-pp prepare` does it ahead)")
        for warm_start in (False, True):
            predictor.prepare(warm_start=warm_start)
    print(f"{predictor.name} on {predictor.backend}, {predictor.precision}; auto threshold {LARGE_DISPARITY_PX:g} px")
    print(report(measure([dataset[i] for i in range(len(dataset))], predictor)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
