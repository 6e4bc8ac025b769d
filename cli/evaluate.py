"""`crestereo-pp eval`: metrics table (and JSON, sheets) of a model, optionally beside SGBM."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from crestereo_pp.stereo_data.readers import LAYOUTS, open_dataset

from .options import add_model_options, inference_options, load_predictor


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Evaluate on every pair of DATA_DIR (Middlebury 2014, ETH3D, KITTI 2012/2015, SceneFlow "
        "or NAME/{left.png,right.png,disp.pfm}). bad-N: percent of valid ground-truth pixels "
        "with |error| > N px; D1-all: error > 3 px and > 5 % of the true disparity."
    )
    parser.add_argument("data_dir", type=Path, metavar="DATA_DIR")
    parser.add_argument("--layout", default="auto", choices=["auto", *LAYOUTS], help="dataset layout [auto]")
    add_model_options(parser)
    parser.add_argument("--baseline", choices=["sgbm"], help="also run this baseline on every pair (OpenCV StereoSGBM)")
    parser.add_argument("--json", type=Path, metavar="OUT", help="write every number to this JSON file")
    parser.add_argument("--sheets", type=Path, metavar="DIR", help="write a comparison sheet PNG per pair here")
    parser.add_argument("--limit", type=int, metavar="N", help="evaluate only the first N pairs")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from crestereo_pp.evaluation.evaluate import evaluate

    dataset = open_dataset(args.data_dir, args.layout)
    if args.limit is not None:
        dataset = dataset[: args.limit]
    predictor = load_predictor(args)
    report = evaluate(
        dataset,
        predictor,
        dataset_name=str(args.data_dir),
        baseline_sgbm=args.baseline == "sgbm",
        sheets_dir=args.sheets,
        options=inference_options(args),
    )
    print(f"{predictor.name} on {predictor.backend}, {predictor.precision}")
    print(report.table())
    print()
    print(report.uncertainty_table())
    calibration = report.calibration_table()
    if calibration:
        print()
        print(calibration)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report.to_dict(), indent=2) + "\n")
    return 0
