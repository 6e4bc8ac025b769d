"""Video: how far warm-started frames drift from cold ones, for a static and a panning camera.

    python bench/sequence.py [--pair middlebury2003_teddy] [--data DIR] [--frames 20]
                             [--size 160x224] [--pan 1 1] [--warm-iters 6 3] [--backend torch]

The camera is a --size (HxW) window onto a real dev pair (--data, by default $STEREO_DEV or
shared/data/stereo-dev; the pair shrunk just enough for the window's travel to fit): fixed
(static), or moving by --pan (dx, dy) px per frame. For each --warm-iters N, one `FrameStream`
computes the frames (the first cold, each next one warm-started from its predecessor, N
iterations at 1/4 and the model's at 1/16 and 1/8), and each frame's disparity is compared with
the cold answer of its pair with as many iterations. Its drift is the mean |warm - cold| (px)
over the pixels whose match, by the cold map, lies inside the right view (x - d >= 0; the strip
left of them has no match, and its answer follows the start). Prints the drift per frame (the
table), then per N the median time of a warm and of a cold frame (the options' cold answer: auto's
quick pass too, from 192 px a side) and the mean and worst drift of each camera.
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from gpu_check.pairs import dev_pairs  # bench/'s sibling package

from crestereo_pp.inference import InferenceOptions, StereoPredictor, load_model
from crestereo_pp.inference.scaling import shrink
from crestereo_pp.stereo_data.formats import read_image

Pair = tuple[np.ndarray, np.ndarray]
"""Left and right views, uint8 HxWx3."""


@dataclass
class Run:
    """One camera's frames through one stream: per warm frame its drift (px) and time (ms), and
    the time of each cold answer computed (ms)."""

    drift: list[float]
    warm_ms: list[float]
    cold_ms: list[float]


def scene(folder: Path, height: int, width: int) -> Pair:
    """The pair in `folder` (left.png, right.png) shrunk, keeping its aspect, to the least size
    that holds `height` x `width` px (no larger than it is)."""
    views = [
        torch.from_numpy(read_image(folder / f"{side}.png")).permute(2, 0, 1)[None].float()
        for side in ("left", "right")
    ]
    full_height, full_width = views[0].shape[-2:]
    factor = max(height / full_height, width / full_width)
    if factor > 1:
        raise SystemExit(f"{folder.name} is {full_width}x{full_height}: too small for {width}x{height} px of travel")
    size = (max(height, round(full_height * factor)), max(width, round(full_width * factor)))
    shrunk = [shrink(view, size)[0].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).numpy() for view in views]
    return shrunk[0], shrunk[1]


def window(pair: Pair, index: int, step: tuple[int, int], height: int, width: int) -> Pair:
    """The `height` x `width` window of `pair` after the camera moved `index` times by `step` = (dx, dy) px."""
    x, y = index * step[0], index * step[1]
    left, right = pair
    return left[y : y + height, x : x + width], right[y : y + height, x : x + width]


def drift(warm: np.ndarray, cold: np.ndarray) -> float:
    """Mean |warm - cold| (px) over the pixels whose match, by `cold`, lies inside the right view."""
    seen = np.arange(cold.shape[1]) - cold >= 0
    return float(np.abs(warm - cold)[seen].mean())


def run_camera(
    predictor: StereoPredictor, pair: Pair, frames: int, step: tuple[int, int], size: tuple[int, int], iters: int
) -> Run:
    """`frames` warm frames (after a cold one) of a camera moving by `step` px per frame."""
    stream = predictor.stream(InferenceOptions(iters=iters), warm_iters=iters)
    result = Run([], [], [])
    cold: np.ndarray | None = None
    for index in range(frames + 1):
        left, right = window(pair, index, step, *size)
        start = time.perf_counter()
        warm = stream.predict(left, right).disparity
        warm_ms = (time.perf_counter() - start) * 1000
        if cold is None or step != (0, 0):  # a static camera's pairs are all the first one
            start = time.perf_counter()
            cold = predictor.predict(left, right, iters=iters).disparity
            result.cold_ms.append((time.perf_counter() - start) * 1000)
        if index > 0:
            result.drift.append(drift(warm, cold))
            result.warm_ms.append(warm_ms)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pair", default="middlebury2003_teddy", help="a dev pair's folder name")
    parser.add_argument("--data", type=Path, help="the dev pairs [$STEREO_DEV, shared/data/stereo-dev]")
    parser.add_argument("--frames", type=int, default=20, help="warm frames, after the first (cold) one")
    parser.add_argument("--size", default="160x224", help="HxW of the camera's window")
    parser.add_argument("--pan", type=int, nargs=2, default=(1, 1), metavar=("DX", "DY"), help="px per frame, >= 0")
    parser.add_argument("--warm-iters", type=int, nargs="+", default=[6, 3], help="iterations at 1/4")
    parser.add_argument("--backend", default="torch", choices=["torch", "openvino", "auto"])
    args = parser.parse_args()
    height, width = (int(side) for side in args.size.split("x"))
    pan = (args.pan[0], args.pan[1])
    if min(pan) < 0:
        raise SystemExit("--pan takes px per frame >= 0")
    data = dev_pairs(args.data)
    if data is None or not (data / args.pair).is_dir():
        raise SystemExit(f"no dev pair {args.pair!r}: pass --data (the folder of the dev pairs)")
    pair = scene(data / args.pair, height + args.frames * pan[1], width + args.frames * pan[0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # untrained weights in a test checkout
        predictor = load_model("lite", backend=args.backend)
    for iters in args.warm_iters:  # OpenVINO: have every graph of the run ready before timing
        predictor.prepare(iters, warm_start=True)  # the graphs of cold and warm starts
    cameras = {"static": (0, 0), f"pan {pan[0]},{pan[1]}": pan}
    runs = {
        (camera, iters): run_camera(predictor, pair, args.frames, step, (height, width), iters)
        for iters in args.warm_iters
        for camera, step in cameras.items()
    }
    print(
        f"lite on {predictor.backend} {predictor.precision}: {args.pair} shrunk to {pair[0].shape[1]}x"
        f"{pair[0].shape[0]}, a {width}x{height} window, {args.frames} warm frames; drift from the cold answer (px)"
    )
    print("| frame | " + " | ".join(f"{camera}, warm {iters}" for camera, iters in runs) + " |")
    print("|---" * (len(runs) + 1) + "|")
    for index in range(args.frames):
        print(f"| {index + 1} | " + " | ".join(f"{run.drift[index]:.3f}" for run in runs.values()) + " |")
    print()
    print("| warm iters | warm ms per frame | cold ms per frame | vs cold | " + " | ".join(cameras) + " |")
    print("|---|---|---|---|" + "---|" * len(cameras))
    for iters in args.warm_iters:
        warm_ms = statistics.median(ms for camera in cameras for ms in runs[camera, iters].warm_ms)
        cold_ms = statistics.median(ms for camera in cameras for ms in runs[camera, iters].cold_ms)
        drifts = " | ".join(
            f"{statistics.mean(runs[camera, iters].drift):.3f} mean, {max(runs[camera, iters].drift):.3f} worst"
            for camera in cameras
        )
        print(f"| {iters} | {warm_ms:.0f} | {cold_ms:.0f} | {cold_ms / warm_ms:.2f}x | {drifts} |")


if __name__ == "__main__":
    main()
