"""`crestereo-pp eval`: metrics table (and JSON, sheets) of a model, optionally beside SGBM."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from evaluation.evaluate import evaluate
from model import load_model
from stereo_data.readers import LAYOUTS, open_dataset
from training.distributed import resolve_device


def add_parser(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "eval",
        help="EPE, bad-1/2/3, D1-all and time per pair and mean, on a dataset with ground truth",
        description=(
            "Evaluate on every pair of DATA_DIR (Middlebury 2014, ETH3D, KITTI 2012/2015, SceneFlow "
            "or NAME/{left.png,right.png,disp.pfm}). bad-N: percent of valid ground-truth pixels "
            "with |error| > N px; D1-all: error > 3 px and > 5 % of the true disparity."
        ),
    )
    parser.add_argument("data_dir", type=Path, metavar="DATA_DIR")
    parser.add_argument("--layout", default="auto", choices=["auto", *LAYOUTS], help="dataset layout [auto]")
    add_model_options(parser)
    parser.add_argument("--baseline", choices=["sgbm"], help="also run this baseline on every pair (OpenCV StereoSGBM)")
    parser.add_argument("--json", type=Path, metavar="OUT", help="write every number to this JSON file")
    parser.add_argument("--sheets", type=Path, metavar="DIR", help="write a comparison sheet PNG per pair here")
    parser.add_argument("--limit", type=int, metavar="N", help="evaluate only the first N pairs")
    parser.set_defaults(run=run)


def add_model_options(parser: argparse.ArgumentParser) -> None:
    """--model, --weights, --device and the inference knobs: shared by eval and predict."""
    parser.add_argument("--model", choices=["lite", "full"], default="lite", help="network [lite]")
    parser.add_argument("--weights", type=Path, help="weights file or checkpoint [the bundled model/weights/MODEL.pt]")
    parser.add_argument("--device", default="auto", help="auto (cuda if available), cpu, cuda, cuda:N [auto]")
    parser.add_argument("--two-pass", action="store_true", help="half-resolution pass, then full-resolution refinement")
    parser.add_argument(
        "--iters",
        type=int,
        nargs="+",
        metavar="N",
        help="ARM iterations: N at 1/4 resolution, or N16 N8 N4 for the three stages [the model's]",
    )
    parser.add_argument(
        "--scale",
        type=float,
        default=1.0,
        help="run the network on the pair resized by this factor in (0, 1] (faster; maps at full size) [1]",
    )


def iterations(args: argparse.Namespace) -> int | tuple[int, int, int] | None:
    """--iters as `StereoPredictor.predict` takes it; a usage error unless 1 or 3 counts."""
    if args.iters is None:
        return None
    if len(args.iters) == 1:
        return args.iters[0]
    if len(args.iters) == 3:
        return (args.iters[0], args.iters[1], args.iters[2])
    raise SystemExit(f"crestereo-pp: --iters takes 1 or 3 counts, got {len(args.iters)}")


def run(args: argparse.Namespace) -> int:
    dataset = open_dataset(args.data_dir, args.layout)
    if args.limit is not None:
        dataset = dataset[: args.limit]
    predictor = load_model(args.model, args.weights, resolve_device(args.device, 0))
    report = evaluate(
        dataset,
        predictor,
        dataset_name=str(args.data_dir),
        baseline_sgbm=args.baseline == "sgbm",
        sheets_dir=args.sheets,
        two_pass=args.two_pass,
        iters=iterations(args),
        scale=args.scale,
    )
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
