"""What a request costs the service, against what its cost model says.

    python bench/request_cost.py [--sizes 256x384,1024x1024,2048x2048] [--pair middlebury2003_teddy]
                                 [--data DIR] [--runs 3] [--requests plain,flip,...] [--backend auto]

The service counts each request's compute in units of a plain request of the same size (one
pass, the model's iterations, every classical step on): `service.batching.stereo.StereoBatches.work`
(`options_cost`, and for `two_pass="auto"` that times the square of the largest enlargement auto
may take: an upper bound). Its queue estimates, `Retry-After` and the per-request cap
(`CRESTEREO_MAX_REQUEST_COST`) rest on it. Here lite computes each request as the service does (a
batch of one through `StereoPredictor.predict_pairs`, iterations without an OpenVINO graph on torch,
as the service would run them), on a dev pair resized to each --size (its disparities scale with
the width). Prints per size and request the modelled cost, the median seconds of --runs calls
(after one untimed call that compiles its shapes), the measured cost (seconds over the plain
request's) and measured / modelled. Heavy requests at 2048x2048 take minutes each.
"""

from __future__ import annotations

import argparse
import statistics
import warnings
from functools import partial
from pathlib import Path

import cv2
import numpy as np
from gpu_check.pairs import dev_pairs  # bench/'s sibling package
from timing import timed_calls  # bench/'s sibling script

from crestereo_pp.inference import InferenceOptions, StereoPredictor, load_model
from crestereo_pp.service.batching.stereo import StereoBatches, stereo_key
from crestereo_pp.stereo_data.formats import read_image

REQUESTS: dict[str, InferenceOptions] = {
    "plain": InferenceOptions(two_pass=False),
    "auto": InferenceOptions(),
    "two-pass": InferenceOptions(two_pass=True),
    "flip": InferenceOptions(two_pass=False, flip=True),
    "scale-0.5": InferenceOptions(two_pass=False, scale=0.5),
    "network-only": InferenceOptions(two_pass=False, blend_sgbm=False, refine_edges=False, align_rows=False),
    "iters-1-1-1": InferenceOptions(two_pass=False, iters=(1, 1, 1)),
    "iters-8-8-16": InferenceOptions(two_pass=False, iters=(8, 8, 16)),
    "iters-16-16-32": InferenceOptions(two_pass=False, iters=(16, 16, 32)),
}
"""The requests timed, by name; `plain` is the unit (one pass, as a plain request is counted)."""


def modelled_cost(predictor: StereoPredictor, options: InferenceOptions, height: int, width: int) -> float:
    """The service's cost of one request of `options` on a `height` x `width` pair, in plain requests
    of that size: the batcher's own units of work (`StereoBatches.work`) over the request's pixels."""
    key = stereo_key("lite", options, height, width)
    return StereoBatches({"lite": predictor}).work(key) / key.pixels


def compute(predictor: StereoPredictor, left: np.ndarray, right: np.ndarray, options: InferenceOptions) -> None:
    """One request as the service computes it: a batch of one, its maps brought to the host."""
    predictor.predict_pairs([left], [right], options).on_host()


def resized(pair: tuple[np.ndarray, np.ndarray], height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Both views resized to `height` x `width` (area averaging where they shrink)."""
    left, right = (cv2.resize(view, (width, height), interpolation=cv2.INTER_AREA) for view in pair)
    return left, right


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="256x384,1024x1024,2048x2048", help="HxW, comma-separated")
    parser.add_argument("--pair", default="middlebury2003_teddy", help="a dev pair's folder name")
    parser.add_argument("--data", type=Path, help="the dev pairs [$STEREO_DEV, shared/data/stereo-dev]")
    parser.add_argument("--runs", type=int, default=3, help="timed calls per request (the median is shown)")
    parser.add_argument("--requests", default=",".join(REQUESTS), help=f"comma-separated, of: {', '.join(REQUESTS)}")
    parser.add_argument("--backend", default="auto", choices=["torch", "openvino", "auto"])
    args = parser.parse_args()
    sizes = [tuple(int(side) for side in size.split("x")) for size in args.sizes.split(",")]
    names = ["plain", *(name for name in args.requests.split(",") if name != "plain")]
    unknown = [name for name in names if name not in REQUESTS]
    if unknown:
        raise SystemExit(f"unknown request {unknown[0]!r}; the requests are {', '.join(REQUESTS)}")
    data = dev_pairs(args.data)
    if data is None or not (data / args.pair).is_dir():
        raise SystemExit(f"no dev pair {args.pair!r}: pass --data (the folder of the dev pairs)")
    pair = (read_image(data / args.pair / "left.png"), read_image(data / args.pair / "right.png"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # untrained weights in a test checkout
        predictor = load_model("lite", backend=args.backend)
    print(f"lite on {predictor.backend} {predictor.precision}: {args.pair} resized; median of {args.runs} calls")
    print("| size | request | modelled | seconds | measured | measured / modelled |")
    print("|---|---|---|---|---|---|")
    for height, width in sizes:
        left, right = resized(pair, height, width)
        plain_seconds = 0.0
        for name in names:
            options = REQUESTS[name]
            call = partial(compute, predictor, left, right, options)
            call()  # compiles its shapes (OpenVINO) and warms the allocator
            seconds = statistics.median(timed_calls(call, args.runs))
            plain_seconds = plain_seconds or seconds
            modelled = modelled_cost(predictor, options, height, width)
            measured = seconds / plain_seconds
            print(
                f"| {height}x{width} | {name} | {modelled:.2f} | {seconds:.3f} | {measured:.2f} "
                f"| {measured / modelled:.2f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
