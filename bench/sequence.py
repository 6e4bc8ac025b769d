"""Video: warm-started frames against cold ones, on a procedural sequence with exact ground truth.

    python bench/sequence.py [--frames 12] [--size 256x512] [--pan 6 1] [--warm-iters 6 3 2]
                             [--backend torch] [--seed 0]

A static procedural scene seen by a camera that pans by --pan (dx, dy) px per frame (content moves
the other way), so every frame's ground truth is known. Each mode runs the whole sequence through
one `FrameStream` (cold: a fresh start every frame; warm N: each frame starts from the previous
one's disparity and refines with N iterations at 1/4 resolution) and prints per mode: median time
per frame (after the first, which is cold in every mode), mean EPE and bad-2 over the frames, and
temporal stability, the mean |d_t(x, y) - d_{t-1}(x + dx, y + dy)| over pixels that both frames
see (the scene is static: any change there is flicker).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing
from model import InferenceOptions, StereoPredictor, load_model  # noqa: E402
from stereo_data.synthetic import SceneConfig, SceneGenerator, SyntheticBatch  # noqa: E402


def sequence(frames: int, height: int, width: int, pan: tuple[float, float], seed: int) -> list[SyntheticBatch]:
    """`frames` renders of one static scene by a camera panning `pan` px per frame (no photometric changes)."""
    generator = SceneGenerator(SceneConfig(height=height, width=width, max_disparity=width / 4, photometric=None))
    return generator.pan(seed, frames, pan)


def run_mode(
    predictor: StereoPredictor, batches: list[SyntheticBatch], warm_iters: int | None, pan: tuple[float, float]
) -> dict[str, float]:
    """One pass over the sequence: warm_iters None means cold every frame."""
    stream = predictor.stream(InferenceOptions(), warm_iters)
    times, epes, bad2s, maps = [], [], [], []
    for batch in batches:
        if warm_iters is None:
            stream.restart()
        start = time.perf_counter()
        prediction = stream.predict(*batch.pair())
        times.append(time.perf_counter() - start)
        truth = batch.disparity[0, 0].numpy()
        error = np.abs(prediction.disparity - truth)
        epes.append(float(error.mean()))
        bad2s.append(float((error > 2).mean() * 100))
        maps.append(prediction.disparity)
    dx, dy = round(pan[0]), round(pan[1])
    changes = []
    for previous, current in zip(maps, maps[1:], strict=False):
        height, width = current.shape
        now = current[: height - dy, : width - dx]
        before = previous[dy:, dx:]
        changes.append(float(np.abs(now - before).mean()))
    return {
        "ms": statistics.median(times[1:]) * 1000,
        "epe": statistics.mean(epes),
        "bad2": statistics.mean(bad2s),
        "flicker": statistics.mean(changes),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--size", default="256x512", help="HxW of the frames")
    parser.add_argument("--pan", type=float, nargs=2, default=(6.0, 1.0), metavar=("DX", "DY"))
    parser.add_argument("--warm-iters", type=int, nargs="+", default=[6, 3, 2])
    parser.add_argument("--backend", default="torch", choices=["torch", "openvino", "auto"])
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    height, width = (int(side) for side in args.size.split("x"))
    pan = (args.pan[0], args.pan[1])
    batches = sequence(args.frames, height, width, pan, args.seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # untrained weights in a test checkout
        predictor = load_model("lite", backend=args.backend)
    predictor.prepare()  # OpenVINO: have every graph of the run ready before timing
    for iters in args.warm_iters:
        predictor.prepare(iters, warm_start=True)
    print(f"lite on {predictor.backend} {predictor.precision}, {args.frames} frames of {args.size}, pan {pan} px/frame")
    print("| mode | ms per frame | vs cold | EPE (px) | bad-2 (%) | flicker (px) |")
    print("|---|---|---|---|---|---|")
    cold = run_mode(predictor, batches, None, pan)
    rows = [("cold", cold)] + [(f"warm, {n} iters", run_mode(predictor, batches, n, pan)) for n in args.warm_iters]
    for name, row in rows:
        print(
            f"| {name} | {row['ms']:.0f} | {cold['ms'] / row['ms']:.2f}x | {row['epe']:.3f} | {row['bad2']:.2f} "
            f"| {row['flicker']:.3f} |"
        )


if __name__ == "__main__":
    main()
