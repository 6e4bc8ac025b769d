"""`crestereo-pp predict`: disparity (and uncertainty, colour) files for one pair or many."""

from __future__ import annotations

import argparse
import glob
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
from tqdm import tqdm

from stereo_data.formats import read_image, write_disparity, write_uncertainty
from stereo_data.pointcloud import Calibration, encode_ply, point_cloud
from stereo_data.visualize import disparity_picture, scale_range

from .options import add_model_options, iterations, load_predictor

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".ppm", ".pgm", ".tif", ".tiff", ".webp"}
DISPARITY_FORMATS = ("pfm", "png", "npy")


@dataclass(frozen=True)
class PairPaths:
    """Input images of one pair and the output `stem` (relative path without extension)."""

    left: Path
    right: Path
    stem: Path


def add_parser(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "predict",
        help="disparity of one rectified pair, or of two folders / globs of pairs",
        description=(
            "LEFT and RIGHT are two image files (OUT is a file: .pfm float with +inf invalid, "
            ".png KITTI 16-bit x256, or .npy float32), two folders (pairs share file names) or two "
            "quoted globs (pairs in sorted order); then OUT, --uncertainty and --color are folders "
            "that mirror the left images' relative paths."
        ),
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
    parser.add_argument("--focal-px", type=float, help="--ply: focal length in px (with --baseline-m: metric points)")
    parser.add_argument("--baseline-m", type=float, help="--ply: stereo baseline in metres")
    parser.add_argument("--cx", type=float, help="--ply: principal point x in px [the image centre]")
    parser.add_argument("--cy", type=float, help="--ply: principal point y in px [the image centre]")
    parser.add_argument("--max-uncertainty", type=float, help="--ply: drop points whose uncertainty is above this")
    parser.add_argument(
        "--raw-uncertainty",
        action="store_true",
        help="write the paper's raw U instead of the calibrated P(error > 2 px) the weights define",
    )
    add_model_options(parser)
    parser.set_defaults(run=run)


def is_single_pair(left: str, right: str) -> bool:
    """True when LEFT and RIGHT name two image files (then OUT names a file, not a folder)."""
    return Path(left).is_file() and Path(right).is_file()


def find_pairs(left: str, right: str) -> list[PairPaths]:
    """Pairs named by LEFT and RIGHT: two files, two folders (matched by file name), or two globs
    (matched in sorted order). Stems are relative to the folder holding all left images."""
    if is_single_pair(left, right):
        return [PairPaths(Path(left), Path(right), Path(Path(left).stem))]
    if Path(left).is_dir() and Path(right).is_dir():
        lefts = {p.name: p for p in Path(left).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES}
        rights = {p.name: p for p in Path(right).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES}
        if set(lefts) != set(rights):
            unmatched = sorted(set(lefts) ^ set(rights))
            raise ValueError(f"{len(unmatched)} image(s) have no partner in the other folder: {unmatched[:5]}")
        return [PairPaths(lefts[name], rights[name], Path(lefts[name].stem)) for name in sorted(lefts)]
    left_paths = [Path(p) for p in sorted(glob.glob(left)) if Path(p).is_file()]
    right_paths = [Path(p) for p in sorted(glob.glob(right)) if Path(p).is_file()]
    if not left_paths:
        raise ValueError(f"no left image matches {left!r}")
    if len(left_paths) != len(right_paths):
        raise ValueError(
            f"{len(left_paths)} left images match {left!r} but {len(right_paths)} right images match {right!r}"
        )
    root = Path(os.path.commonpath([p.parent.resolve() for p in left_paths]))
    return [
        PairPaths(left_path, right_path, left_path.resolve().relative_to(root).with_suffix(""))
        for left_path, right_path in zip(left_paths, right_paths, strict=True)
    ]


def run(args: argparse.Namespace) -> int:
    if (args.focal_px is None) != (args.baseline_m is None):
        raise ValueError("give both --focal-px and --baseline-m, or neither")
    pairs = find_pairs(args.left, args.right)
    single = is_single_pair(args.left, args.right)
    predictor = load_predictor(args)
    calibration = None if args.focal_px is None else Calibration(args.focal_px, args.baseline_m, args.cx, args.cy)
    for pair in tqdm(pairs, desc=f"predict {args.model}", unit="pair", disable=single):
        left = read_image(pair.left)
        prediction = predictor.predict(
            left,
            read_image(pair.right),
            iters=iterations(args),
            two_pass=args.two_pass,
            scale=args.scale,
            raw_uncertainty=args.raw_uncertainty,
        )
        disparity_path = args.output if single else args.output / f"{pair.stem}.{args.format}"
        disparity_path.parent.mkdir(parents=True, exist_ok=True)
        write_disparity(disparity_path, prediction.disparity)
        if args.uncertainty is not None:
            uncertainty_path = args.uncertainty if single else args.uncertainty / f"{pair.stem}.pfm"
            uncertainty_path.parent.mkdir(parents=True, exist_ok=True)
            write_uncertainty(uncertainty_path, prediction.uncertainty)
        if args.color is not None:
            color_path = args.color if single else args.color / f"{pair.stem}.png"
            color_path.parent.mkdir(parents=True, exist_ok=True)
            scale = scale_range(prediction.disparity, args.color_min, args.color_max)
            picture = disparity_picture(prediction.disparity, scale)
            cv2.imwrite(str(color_path), picture[:, :, ::-1])
        if args.ply is not None:
            ply_path = args.ply if single else args.ply / f"{pair.stem}.ply"
            ply_path.parent.mkdir(parents=True, exist_ok=True)
            points, colours = point_cloud(
                prediction.disparity, left, prediction.uncertainty, calibration, args.max_uncertainty
            )
            ply_path.write_bytes(encode_ply(points, colours))
    if single:
        print(f"wrote {args.output}")
    else:
        print(f"wrote {len(pairs)} disparity maps to {args.output}")
    return 0
