"""`crestereo-pp calibrate`: fit what the uncertainty map means for a weights file, and store it."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Run the network on procedural validation scenes (never real pairs), fit the map from "
        "the paper's uncertainty U and features of each pixel's answer (disparity edges, texture, "
        "matches outside the right image, how well the right image matches there and nearby) to the "
        "probability of an error above 2 px, and store it in "
        "WEIGHTS, replacing any earlier one. Run it whenever the weights change. Needs the train "
        "extra (pip install 'crestereo-pp[train]')."
    )
    parser.add_argument("weights", type=Path, metavar="WEIGHTS", help="weights file or checkpoint (rewritten)")
    parser.add_argument(
        "--scenes",
        type=int,
        default=32,
        help="procedural scenes to fit on [32]",
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    try:
        from crestereo_pp.training.calibrate import calibrate_weights_file
    except ModuleNotFoundError as error:
        raise SystemExit(
            f"crestereo-pp calibrate: needs {error.name}, from the train extra: pip install 'crestereo-pp[train]'"
        ) from None
    calibration = calibrate_weights_file(args.weights, args.scenes)
    low, high = calibration.probabilities[0], calibration.probabilities[-1]
    print(
        f"{args.weights}: uncertainty = P(error > {calibration.threshold_px:g} px), from {low:.3f} to {high:.3f}; "
        f"fitted on {calibration.fitted_on}"
    )
    return 0
