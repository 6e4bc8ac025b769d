"""`crestereo-pp eval`: metrics table (and JSON, sheets) of a model, optionally beside SGBM."""

from __future__ import annotations

import argparse
import json
import typing
from collections.abc import Sequence
from pathlib import Path

from crestereo_pp.stereo_data.readers import LAYOUTS, StereoSample, open_dataset

from .options import add_model_options, inference_options, load_predictor

PROCEDURAL_SEED = 3 * 2**30
"""First seed of `--procedural` scenes: above every training seed, a billion above the
calibration's (``synthetic.draw.SEEDS``)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Evaluate on every pair of DATA_DIR (Middlebury 2014, ETH3D, KITTI 2012/2015, SceneFlow "
        "or NAME/{left.png,right.png,disp.pfm}). bad-N: percent of valid ground-truth pixels "
        "with |error| > N px; D1-all: error > 3 px and > 5 % of the true disparity."
    )
    parser.add_argument("data_dir", type=Path, metavar="DATA_DIR", nargs="?", help="real pairs (or --procedural)")
    parser.add_argument("--layout", default="auto", choices=["auto", *LAYOUTS], help="dataset layout [auto]")
    procedural = parser.add_argument_group("procedural scenes (instead of DATA_DIR)")
    procedural.add_argument(
        "--procedural",
        action="store_true",
        help="evaluate on scenes of the training generator (exact ground truth, seeds no training run "
        "draws) instead of DATA_DIR: how a model does on one kind of scene, such as a hard case",
    )
    procedural.add_argument(
        "--scene",
        action="append",
        default=[],
        type=scene_setting,
        metavar="KEY=VALUE",
        help="a numeric setting of those scenes (SceneConfig), e.g. thin_probability=1 or max_disparity=96; "
        "repeat it for more",
    )
    procedural.add_argument("--scenes", type=positive, default=16, metavar="N", help="how many scenes [16]")
    procedural.add_argument("--size", type=scene_size, default=(256, 512), metavar="HxW", help="their size [256x512]")
    procedural.add_argument("--seed", type=int, default=PROCEDURAL_SEED, help=f"first seed [{PROCEDURAL_SEED}]")
    add_model_options(parser)
    parser.add_argument("--baseline", choices=["sgbm"], help="also run this baseline on every pair (OpenCV StereoSGBM)")
    parser.add_argument("--json", type=Path, metavar="OUT", help="write every number to this JSON file")
    parser.add_argument("--sheets", type=Path, metavar="DIR", help="write a comparison sheet PNG per pair here")
    parser.add_argument("--limit", type=int, metavar="N", help="evaluate only the first N pairs")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    dataset, name = evaluation_pairs(args)  # first: pairs it cannot take are refused before torch loads
    from crestereo_pp.evaluation.evaluate import evaluate

    if args.limit is not None:
        dataset = dataset[: args.limit]
    predictor = load_predictor(args)
    report = evaluate(
        dataset,
        predictor,
        dataset_name=name,
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


def evaluation_pairs(args: argparse.Namespace) -> tuple[Sequence[StereoSample], str]:
    """The pairs to evaluate and their name: DATA_DIR's, or procedural scenes with --procedural
    (ValueError, which the command line reports, for a choice it cannot take)."""
    if args.procedural == (args.data_dir is not None):
        raise ValueError("give either DATA_DIR or --procedural")
    if not args.procedural:
        if args.scene:
            raise ValueError("--scene sets procedural scenes: add --procedural")
        return open_dataset(args.data_dir, args.layout), str(args.data_dir)
    import torch

    from crestereo_pp.stereo_data.synthetic import SceneConfig, SceneGenerator

    height, width = args.size
    config = SceneConfig(height=height, width=width, **dict(args.scene))
    settings = " ".join(f"{key}={value:g}" for key, value in args.scene)
    name = (
        f"{args.scenes} procedural scenes {height}x{width}{' ' + settings if settings else ''}, seeds from {args.seed}"
    )
    return SceneGenerator(config, device=torch.device("cpu")).samples(args.scenes, args.seed), name


def scene_setting(text: str) -> tuple[str, float]:
    """--scene KEY=VALUE: a numeric field of SceneConfig (int, float, or either or None) and its
    value, of the field's type; the size is --size's."""
    from crestereo_pp.stereo_data.synthetic import SceneConfig

    from .dataclass_args import strip_optional

    key, separator, value = text.partition("=")
    numeric = {
        name: kind
        for name, kind in ((name, strip_optional(hint)) for name, hint in typing.get_type_hints(SceneConfig).items())
        if kind in (int, float) and name not in ("height", "width")
    }
    if not separator or key not in numeric:
        raise argparse.ArgumentTypeError(
            f"expected KEY=VALUE with KEY one of the numeric scene settings: {', '.join(sorted(numeric))}"
        )
    kind = numeric[key]
    try:
        return key, kind(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{key} takes a number ({kind.__name__}), got {value!r}") from None


def scene_size(text: str) -> tuple[int, int]:
    """--size HxW: the scenes' height and width in pixels."""
    height, separator, width = text.partition("x")
    if not (separator and height.isdigit() and width.isdigit() and int(height) > 0 and int(width) > 0):
        raise argparse.ArgumentTypeError(f"expected HEIGHTxWIDTH in pixels, such as 256x512, got {text!r}")
    return int(height), int(width)


def positive(text: str) -> int:
    """A count of at least one."""
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"expected a positive whole number, got {text!r}")
    return int(text)
