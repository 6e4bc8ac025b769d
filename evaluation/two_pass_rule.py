"""Where two-pass inference and enlarging pay, pair by pair: the evidence ``two_pass="auto"``
decides by (the 99th percentile of a quick quarter-resolution pass's disparity) beside bad-2 and
EPE of one pass at the pair's size, of one pass on the pair enlarged by each of
``inference.two_pass.ENLARGEMENTS``, and of two passes; what auto picks; and the mean bad-2 that
each two-pass threshold between the pairs' evidence would give. How ``LARGE_DISPARITY_PX`` and
``ENLARGED_DISPARITY_PX`` are measured for new weights:

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
from crestereo_pp.inference.scaling import maps_at, resize_images
from crestereo_pp.inference.two_pass import ENLARGEMENTS, LARGE_DISPARITY_PX, AutoWay, auto_way
from crestereo_pp.stereo_data.readers import StereoSample, open_dataset


@dataclass(frozen=True)
class PairRule:
    """One pair: the auto rule's evidence (px), its size, and the metrics of one pass at its size,
    of one pass enlarged by each factor of ENLARGEMENTS, and of two passes."""

    name: str
    evidence_px: float
    size: tuple[int, int]
    one: DisparityMetrics
    two: DisparityMetrics
    enlarged: dict[float, DisparityMetrics]

    def way(self, threshold_px: float = LARGE_DISPARITY_PX, enlarge: bool = True) -> AutoWay:
        """What auto computes with two passes above `threshold_px` (``auto_way``)."""
        return auto_way(self.evidence_px, *self.size, enlarge=enlarge, large_px=threshold_px)

    def metrics(self, way: AutoWay) -> DisparityMetrics:
        two_passes, factor = way
        return self.two if two_passes else self.enlarged.get(factor, self.one)

    def bad2(self, threshold_px: float, enlarge: bool = True) -> float:
        return self.metrics(self.way(threshold_px, enlarge)).bad2


def measure(samples: Sequence[StereoSample], predictor: StereoPredictor) -> list[PairRule]:
    """Each pair computed in one pass at its size and enlarged, and in two passes, with the
    evidence the auto rule reads."""
    rules = []
    for sample in samples:
        known = sample.valid & np.isfinite(sample.disparity)
        left, right = (as_image_batch(image, predictor.device) for image in (sample.left, sample.right))
        evidence = predictor.large_disparity_percentile(left, right)
        one, two = (predictor.predict(sample.left, sample.right, two_pass=flag).disparity for flag in (False, True))
        height, width = sample.left.shape[:2]
        enlarged = {}
        for factor in ENLARGEMENTS:
            size = (round(height * factor), round(width * factor))
            maps = predictor.predict(resize_images(left, size), resize_images(right, size), two_pass=False)
            disparity, _ = maps_at((maps.disparity[:, None], maps.uncertainty[:, None]), height, width)
            enlarged[factor] = compute_metrics(disparity[0, 0].cpu().numpy(), sample.disparity, known)
        rules.append(
            PairRule(
                sample.name,
                float(evidence[0]),
                (height, width),
                compute_metrics(one, sample.disparity, known),
                compute_metrics(two, sample.disparity, known),
                enlarged,
            )
        )
    return rules


def thresholds_between(rules: Sequence[PairRule]) -> list[float]:
    """Candidate thresholds: below every pair's evidence, between each two neighbours, above all."""
    evidence = sorted(rule.evidence_px for rule in rules)
    middles = [(low + high) / 2 for low, high in zip(evidence, evidence[1:], strict=False)]
    return [evidence[0] - 1.0, *middles, evidence[-1] + 1.0]


def way_name(way: AutoWay) -> str:
    two_passes, factor = way
    return "two" if two_passes else f"{factor:g}x"


def report(rules: Sequence[PairRule], threshold_px: float = LARGE_DISPARITY_PX) -> str:
    """The per-pair table, its means, and the threshold sweep, as text."""
    factors = sorted({factor for rule in rules for factor in rule.enlarged})
    enlarged_header = "".join(f" {f'{factor:g}x':>6}" for factor in factors)
    lines = [
        f"{'pair':34} {'p99 px':>7} {'auto':>5} {'bad-2 1x':>8}{enlarged_header} {'two':>6} {'EPE 1x':>7} {'two':>6}",
        "-" * (82 + 7 * len(factors)),
    ]
    for rule in rules:
        enlarged = "".join(f" {rule.enlarged[factor].bad2:6.2f}" for factor in factors)
        lines.append(
            f"{rule.name[:34]:34} {rule.evidence_px:7.1f} {way_name(rule.way(threshold_px)):>5} "
            f"{rule.one.bad2:8.2f}{enlarged} {rule.two.bad2:6.2f} {rule.one.epe:7.3f} {rule.two.epe:6.3f}"
        )

    def mean(values: Sequence[float]) -> float:
        return statistics.fmean(values)

    everywhere = ", ".join(f"{factor:g}x {mean([r.enlarged[factor].bad2 for r in rules]):.2f}" for factor in factors)
    lines += [
        "",
        f"mean bad-2: one pass {mean([r.one.bad2 for r in rules]):.2f}, enlarged everywhere {everywhere}, "
        f"two passes {mean([r.two.bad2 for r in rules]):.2f}",
        f"auto at {threshold_px:g} px: {mean([r.bad2(threshold_px) for r in rules]):.2f} "
        f"(bad-1 {mean([r.metrics(r.way(threshold_px)).bad1 for r in rules]):.2f}, "
        f"EPE {mean([r.metrics(r.way(threshold_px)).epe for r in rules]):.3f}); "
        f"without enlarging {mean([r.bad2(threshold_px, enlarge=False) for r in rules]):.2f}",
        "mean bad-2 of auto by threshold (two passes where p99 > threshold):",
    ]
    for threshold in thresholds_between(rules):
        picked = sum(rule.way(threshold)[0] for rule in rules)
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
