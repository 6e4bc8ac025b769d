"""One camera's requests under the default inference: time per request for each way
``two_pass="auto"`` may compute its pairs, and alternating between two of them, at each bound of
OpenVINO's compiled shapes (``CRESTEREO_COMPILED_MB``; ``load_model(compiled_bytes=...)``).

    python bench/camera_shapes.py [--pair kitti2015_000001_10] [--data DIR] [--calls 5]
                                  [--compiled-mb 768 1856] [--backend openvino] [--precision auto]

Each request is what auto runs for a pair it computes that way: the quick quarter-resolution pass,
then the way (``inference.two_pass.way_maps``: one pass or two, on the pair enlarged by the
factor), on the real dev pair --pair (--data, by default $STEREO_DEV or shared/data/stereo-dev).
Where a camera's shapes do not fit in the bound, they evict one another and its requests compile
again from OpenVINO's disk cache each time. Per bound (a fresh predictor), per scenario: the
median of --calls requests after one untimed, and each call's time. On torch (--backend torch)
nothing is compiled and the bound changes nothing.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from gpu_check.pairs import dev_pairs  # bench/'s sibling package

from crestereo_pp.inference import StereoPredictor, load_model
from crestereo_pp.inference.prediction import as_image_batch
from crestereo_pp.inference.two_pass import AutoWay, large_disparity_percentile, way_maps
from crestereo_pp.stereo_data.formats import read_image

SCENARIOS: dict[str, tuple[AutoWay, ...]] = {
    "one pass, 1.25x": ((False, 1.25),),
    "one pass, 1.5x": ((False, 1.5),),
    "one pass, 1.25x and 1.5x in turn": ((False, 1.25), (False, 1.5)),
    "two passes, 1.5x": ((True, 1.5),),
    "one pass 1x and two passes 1.5x in turn": ((False, 1.0), (True, 1.5)),
}
"""The requests of each scenario, in turn: the way each is computed."""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pair", default="kitti2015_000001_10", help="a dev pair's folder name")
    parser.add_argument("--data", type=Path, help="the dev pairs [$STEREO_DEV, shared/data/stereo-dev]")
    parser.add_argument("--calls", type=int, default=5, help="timed requests per scenario")
    parser.add_argument("--compiled-mb", type=int, nargs="+", default=[768, 1856], help="the bounds to compare")
    parser.add_argument("--backend", choices=["openvino", "torch"], default="openvino")
    parser.add_argument(
        "--precision", choices=["auto", "fp32", "bf16"], default="auto", help="auto: the default on this CPU"
    )
    args = parser.parse_args()
    folder = dev_pairs(args.data)
    if folder is None:
        raise SystemExit("no dev pairs found: --data DIR")
    left, right = (read_image(folder / args.pair / f"{side}.png") for side in ("left", "right"))
    size = f"{left.shape[1]}x{left.shape[0]}"
    print(f"{args.pair} ({size}), {args.backend}, {args.precision}; median of {args.calls} requests")
    print("\n| scenario | compiled MiB | ms per request | each (ms) |\n|---|---|---|---|")
    for megabytes in args.compiled_mb:
        predictor = load_model("lite", backend=args.backend, precision=args.precision, compiled_bytes=megabytes << 20)
        predictor.prepare(wait=True)
        for name, ways in SCENARIOS.items():
            for way in ways:
                request(predictor, left, right, way)  # each shape compiled (or read from the cache) once, untimed
            times = [request(predictor, left, right, ways[i % len(ways)]) for i in range(args.calls)]
            each = ", ".join(f"{t:.0f}" for t in times)
            print(f"| {name} | {megabytes} | {statistics.median(times):.0f} | {each} |", flush=True)


def request(predictor: StereoPredictor, left: np.ndarray, right: np.ndarray, way: AutoWay) -> float:
    """Milliseconds of one request computed `way`, after auto's quick pass, on the predictor's backend."""
    forward = predictor.padded_forward()
    iters = predictor.config.iters
    left_batch, right_batch = (as_image_batch(image, predictor.device) for image in (left, right))
    started = time.perf_counter()
    with torch.inference_mode():
        large_disparity_percentile(left_batch, right_batch, iters, forward)
        way_maps(left_batch, right_batch, iters, way, forward)
    return 1000 * (time.perf_counter() - started)


if __name__ == "__main__":
    main()
