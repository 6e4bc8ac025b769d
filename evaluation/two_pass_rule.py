"""Where two-pass inference and enlarging pay, pair by pair: the evidence ``two_pass="auto"``
decides by (the 99th percentile of a quick quarter-resolution pass's disparity) beside bad-2 of
each way auto may compute a pair (one pass or two, at the pair's size or enlarged by each of
``inference.two_pass.ENLARGEMENTS``), what auto picks, and the mean bad-2 that each two-pass
threshold between the pairs' evidence would give. How ``LARGE_DISPARITY_PX`` and
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
import torch

from crestereo_pp.evaluation.metrics import DisparityMetrics, compute_metrics
from crestereo_pp.inference import StereoPredictor, load_model
from crestereo_pp.inference.prediction import as_image_batch
from crestereo_pp.inference.two_pass import ENLARGEMENTS, LARGE_DISPARITY_PX, AutoWay, auto_way, way_maps
from crestereo_pp.stereo_data.readers import StereoSample, open_dataset

WAYS: tuple[AutoWay, ...] = tuple((two, factor) for two in (False, True) for factor in (1.0, *ENLARGEMENTS))
"""Every way auto may compute a pair of the sizes it enlarges: one pass or two, at its size or
enlarged (a pair it shrinks is also measured the way auto shrinks it, ``measure``)."""


@dataclass(frozen=True)
class PairRule:
    """One pair: the auto rule's evidence (px), its size, and the metrics of each of WAYS."""

    name: str
    evidence_px: float
    size: tuple[int, int]
    ways: dict[AutoWay, DisparityMetrics]

    def way(self, threshold_px: float = LARGE_DISPARITY_PX, resize: bool = True) -> AutoWay:
        """What auto computes with two passes above `threshold_px` (``auto_way``)."""
        return auto_way(self.evidence_px, *self.size, resize=resize, large_px=threshold_px)

    def bad2(self, threshold_px: float, resize: bool = True) -> float:
        return self.ways[self.way(threshold_px, resize)].bad2


def measure(samples: Sequence[StereoSample], predictor: StereoPredictor) -> list[PairRule]:
    """Each pair computed each of WAYS (``two_pass.way_maps``, on the predictor's backend), and
    shrunk in two passes where auto would shrink it at every threshold below its evidence
    (``auto_way``), with the evidence the auto rule reads."""
    forward = predictor.padded_forward()
    rules = []
    for sample in samples:
        known = sample.valid & np.isfinite(sample.disparity)
        left, right = (as_image_batch(image, predictor.device) for image in (sample.left, sample.right))
        evidence = float(predictor.large_disparity_percentile(left, right)[0])
        height, width = sample.left.shape[:2]
        ways = {}
        for way in dict.fromkeys((*WAYS, auto_way(evidence, height, width, large_px=0.0))):
            with torch.inference_mode():
                disparity, _ = way_maps(left, right, predictor.config.iters, way, forward)
            ways[way] = compute_metrics(disparity[0, 0].cpu().numpy(), sample.disparity, known)
        rules.append(PairRule(sample.name, evidence, (height, width), ways))
    return rules


def thresholds_between(rules: Sequence[PairRule]) -> list[float]:
    """Candidate thresholds: below every pair's evidence, between each two neighbours, above all."""
    evidence = sorted(rule.evidence_px for rule in rules)
    middles = [(low + high) / 2 for low, high in zip(evidence, evidence[1:], strict=False)]
    return [evidence[0] - 1.0, *middles, evidence[-1] + 1.0]


def way_name(way: AutoWay) -> str:
    two_passes, factor = way
    return f"{'two' if two_passes else 'one'} {factor:g}x"


def report(rules: Sequence[PairRule], threshold_px: float = LARGE_DISPARITY_PX) -> str:
    """The per-pair table, its means, and the threshold sweep, as text."""
    ways = [way for way in WAYS if all(way in rule.ways for rule in rules)]
    header = "".join(f" {way_name(way):>9}" for way in ways)
    lines = [
        f"{'pair':34} {'p99 px':>7} {'auto':>9} | bad-2 %{header}",
        "-" * (62 + 10 * len(ways)),
    ]
    for rule in rules:
        values = "".join(f" {rule.ways[way].bad2:9.2f}" for way in ways)
        picked = way_name(rule.way(threshold_px))
        lines.append(f"{rule.name[:34]:34} {rule.evidence_px:7.1f} {picked:>9} |        {values}")

    def mean(values: Sequence[float]) -> float:
        return statistics.fmean(values)

    chosen = [rule.ways[rule.way(threshold_px)] for rule in rules]
    lines += [
        "",
        "mean bad-2, each way everywhere: "
        + ", ".join(f"{way_name(way)} {mean([r.ways[way].bad2 for r in rules]):.2f}" for way in ways),
        f"auto at {threshold_px:g} px: bad-2 {mean([m.bad2 for m in chosen]):.2f}, bad-1 "
        f"{mean([m.bad1 for m in chosen]):.2f}, EPE {mean([m.epe for m in chosen]):.3f}; "
        f"without resizing: bad-2 {mean([r.bad2(threshold_px, resize=False) for r in rules]):.2f}",
        "mean bad-2 of auto by threshold (two passes where p99 > threshold):",
    ]
    for threshold in thresholds_between(rules):
        in_two = sum(rule.way(threshold)[0] for rule in rules)
        lines.append(f"  {threshold:7.1f} px: {mean([r.bad2(threshold) for r in rules]):6.2f} ({in_two} pairs in two)")
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
