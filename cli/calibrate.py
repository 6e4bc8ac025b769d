"""`crestereo-pp calibrate`: fit what the uncertainty map means for a weights file, and store it."""

from __future__ import annotations

import argparse
from pathlib import Path

from training.calibrate import CALIBRATION_SCENES, calibrate_weights_file


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = commands.add_parser(
        "calibrate",
        help="fit P(error > 2 px) from the uncertainty on procedural scenes; store it in the weights",
        description=(
            "Run the network on procedural validation scenes (never real pairs), fit the map from "
            "the paper's uncertainty U to the probability of an error above 2 px, and store it in "
            "WEIGHTS, replacing any earlier one. Run it whenever the weights change."
        ),
    )
    parser.add_argument("weights", type=Path, metavar="WEIGHTS", help="weights file or checkpoint (rewritten)")
    parser.add_argument(
        "--scenes",
        type=int,
        default=24,
        help=f"procedural {CALIBRATION_SCENES.height}x{CALIBRATION_SCENES.width} scenes to fit on [24]",
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    calibration = calibrate_weights_file(args.weights, args.scenes)
    low, high = calibration.probabilities[0], calibration.probabilities[-1]
    print(
        f"{args.weights}: uncertainty = P(error > {calibration.threshold_px:g} px), from {low:.3f} to {high:.3f} "
        f"over U in [{calibration.knots[0]:.3f}, {calibration.knots[-1]:.3f}]; fitted on {calibration.fitted_on}"
    )
    return 0
