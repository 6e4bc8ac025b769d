"""Command-line options that several commands share: the model, its weights, device and knobs."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from model import TWO_PASS_CHOICES, InferenceOptions, StereoPredictor, load_model, parse_iterations, parse_two_pass
from model.config import MODEL_NAMES
from model.device import resolve_device


def add_model_options(parser: argparse.ArgumentParser) -> None:
    """--model, --weights, --device and the inference knobs: shared by eval and predict."""
    parser.add_argument("--model", choices=MODEL_NAMES, default="lite", help="network [lite]")
    parser.add_argument("--weights", type=Path, help="weights file or checkpoint [the bundled model/weights/MODEL.pt]")
    parser.add_argument("--device", default="auto", help="auto (cuda if available), cpu, cuda, cuda:N [auto]")
    parser.add_argument(
        "--backend",
        choices=["auto", "torch", "openvino"],
        default="auto",
        help="auto: $CRESTEREO_BACKEND if set, else OpenVINO on a CPU (compiled: 2-3x faster), torch on a GPU [auto]",
    )
    parser.add_argument(
        "--precision",
        choices=["auto", "fp32", "bf16"],
        default="auto",
        help="auto: bf16 with OpenVINO on a CPU that computes bf16 natively (AMX, AVX512-BF16), else fp32 [auto]",
    )
    parser.add_argument(
        "--two-pass",
        choices=TWO_PASS_CHOICES,
        nargs="?",
        const="on",
        default="auto",
        help="a half-resolution pass, then full-resolution refinement from it: on (the flag alone), off, "
        "or auto: where a quick quarter-resolution pass finds large disparities (above about 90 px) [auto]",
    )
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


def inference_options(args: argparse.Namespace) -> InferenceOptions:
    """--iters, --two-pass, --scale (and --raw-uncertainty where the command has it) as one value;
    a usage error where they are invalid."""
    try:
        return InferenceOptions(
            parse_iterations(args.iters),
            parse_two_pass(args.two_pass),
            args.scale,
            getattr(args, "raw_uncertainty", False),
        )
    except ValueError as error:
        raise SystemExit(f"crestereo-pp: {error}") from None


def load_predictor(args: argparse.Namespace) -> StereoPredictor:
    """The predictor that --model, --weights, --device, --backend and --precision name, with the
    fast path for --iters and --two-pass ready: a graph that is not in the cache yet is exported
    now, saying so (once per weights and iterations; later runs read it from the cache)."""
    predictor = load_model(
        args.model,
        args.weights,
        resolve_device(args.device, 0),
        backend=args.backend,
        precision=args.precision,
    )
    options = inference_options(args)
    for warm_start in (False, True) if options.two_pass is not False else (False,):
        if not predictor.prepare(options.iters, warm_start=warm_start, wait=False):
            print(
                f"crestereo-pp: compiling {args.model} for OpenVINO ({'warm' if warm_start else 'cold'} start), once: "
                "about a minute; later runs read it from the cache",
                file=sys.stderr,
            )
            if not predictor.prepare(options.iters, warm_start=warm_start, wait=True):
                print("crestereo-pp: the OpenVINO export failed (see the log); running on torch", file=sys.stderr)
    return predictor
