"""`crestereo-pp predict`: disparity (and uncertainty, colour) files for one pair or many.

Its arguments; what it does is in `cli.prediction` (and with --ray `cli.ray_predict`), imported
when it runs.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from crestereo_pp.stereo_data.pointcloud import MIN_DISPARITY

from .options import add_model_options

DISPARITY_FORMATS = ("pfm", "png", "npy")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "LEFT and RIGHT are two image files (OUT is a file: .pfm float with +inf invalid, "
        ".png KITTI 16-bit x256, or .npy float32), two folders (pairs share file names), two "
        "quoted globs (pairs in sorted order) or two video files (frame by frame); then OUT, "
        "--uncertainty and --color are folders that mirror the left images' relative paths "
        "(a video's frames are frame_000000 and on). With --sequence the pairs are the frames of "
        "one camera, each warm-started from the previous one."
    )
    parser.add_argument("left", help="left image, folder or glob")
    parser.add_argument("right", help="right image, folder or glob")
    parser.add_argument("-o", "--output", type=Path, required=True, help="disparity file (.pfm/.png/.npy) or folder")
    parser.add_argument(
        "--format", choices=DISPARITY_FORMATS, default="pfm", help="disparity format in folder mode [pfm]"
    )
    parser.add_argument(
        "--uncertainty",
        type=Path,
        metavar="U_OUT",
        help="uncertainty in [0, 1]: .pfm/.npy float, .png 16-bit x65535 (folder mode: a folder of .pfm)",
    )
    parser.add_argument("--color", type=Path, metavar="PNG", help="colour-mapped disparity PNG (folder mode: a folder)")
    parser.add_argument(
        "--color-min",
        type=float,
        metavar="PX",
        help="disparity at the bottom of the colour scale [each map's 1st percentile]",
    )
    parser.add_argument(
        "--color-max",
        type=float,
        metavar="PX",
        help="disparity at the top of the colour scale [each map's 99th percentile]",
    )
    parser.add_argument(
        "--ply",
        type=Path,
        metavar="PLY",
        help="binary PLY point cloud coloured by the left image (folder mode: a folder)",
    )
    parser.add_argument(
        "--depth",
        type=Path,
        metavar="D_OUT",
        help="metric depth in metres (needs --focal-px and --baseline-m): .pfm/.npy float with +inf where there is "
        "none, .png KITTI 16-bit x256 with 0 (folder mode: a folder of .pfm)",
    )
    parser.add_argument(
        "--depth-mm",
        type=Path,
        metavar="PNG",
        help="metric depth as a 16-bit PNG in millimetres, as RealSense, Kinect and Open3D (depth_scale=1000) "
        "read it: 0 where there is none or beyond 65.535 m (needs what --depth needs; folder mode: a folder)",
    )
    parser.add_argument(
        "--calibration",
        type=Path,
        nargs="+",
        metavar="FILE",
        help="the pair is raw, from this calibrated camera: one OpenCV file (K1, D1, K2, D2, R, T, image size; "
        "YAML or JSON) or two ROS camera_info files (left, right). The pair is rectified first; depth and "
        "metric points then need no --focal-px/--baseline-m (the rectified camera's are printed)",
    )
    parser.add_argument(
        "--frame",
        choices=["rectified", "original"],
        default="rectified",
        help="with --calibration: maps in the rectified left image, or resampled into the original left image's "
        "pixels (depth along that camera's axis; +inf disparity and depth, uncertainty 1, where a pixel has no "
        "rectified counterpart) [rectified]",
    )
    parser.add_argument("--focal-px", type=float, help="focal length in px (with --baseline-m: depth, metric points)")
    parser.add_argument("--baseline-m", type=float, help="stereo baseline in metres")
    parser.add_argument("--cx", type=float, help="--ply: principal point x in px [the image centre]")
    parser.add_argument("--cy", type=float, help="--ply: principal point y in px [the image centre]")
    parser.add_argument("--max-uncertainty", type=float, help="--ply: drop points whose uncertainty is above this")
    parser.add_argument(
        "--min-disparity",
        type=float,
        default=MIN_DISPARITY,
        metavar="PX",
        help=f"--depth, --ply: no depth and no point at or below this disparity [{MIN_DISPARITY:g}]",
    )
    parser.add_argument(
        "--max-depth-m", type=float, metavar="M", help="--depth, --ply: no depth and no point beyond this depth"
    )
    parser.add_argument(
        "--sequence",
        action="store_true",
        help="the pairs are consecutive frames of one camera (sorted folders or globs, or two videos): each "
        "starts from the previous one's disparity (steadier and faster; a frame of another size starts cold)",
    )
    parser.add_argument(
        "--warm-iters",
        type=int,
        metavar="N",
        help="--sequence: iterations at 1/4 resolution of warm-started frames [those of --iters]",
    )
    parser.add_argument("--mkdir", action="store_true", help="create missing output folders (else they are an error)")
    parser.add_argument(
        "--raw-uncertainty",
        action="store_true",
        help="write the paper's raw U instead of the calibrated P(error > 2 px) the weights define",
    )
    add_model_options(parser)
    service = parser.add_argument_group("a running service (the pairs computed there)")
    service.add_argument(
        "--url",
        help="compute the pairs on the service at this address (`crestereo-pp serve`, the container) with "
        "--model and the options above, instead of with a model here; the outputs are written here as ever "
        "(raw pairs rectified here first; with --sequence the frames go over one stream)",
    )
    service.add_argument(
        "--api-key",
        default=os.environ.get("CRESTEREO_API_KEY") or None,
        help="--url: the service's bearer key [$CRESTEREO_API_KEY]",
    )
    ray = parser.add_argument_group("Ray (many pairs over a cluster)")
    ray.add_argument(
        "--ray",
        action="store_true",
        help="folders or globs of pairs as a Ray job: a pool of workers, each loading the model once; pairs whose "
        "outputs all exist are skipped (a re-run finishes an interrupted job); a pair that fails is reported and "
        "the others go on (needs the `ray` extra)",
    )
    ray.add_argument(
        "--address", help="--ray: an existing Ray cluster (`auto`, or the head's host:port) [a local one, started here]"
    )
    ray.add_argument(
        "--workers", type=int, metavar="N", help="--ray: workers, each with an equal share of the CPUs [one per CPU]"
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from . import prediction

    job = prediction.prepare(args)
    if args.ray:
        from .ray_predict import run_on_ray

        return run_on_ray(job)
    return prediction.run(job)
