"""Command-line options that several commands share: the model, its weights, device and knobs.

Defining them imports nothing heavy (the `model` package imports torch): that happens in the
functions that load a model, once the arguments are parsed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from crestereo_pp.inference import InferenceOptions, Iterations, StereoPredictor
    from crestereo_pp.inference.backend_choice import BackendChoice

MODEL_NAMES = ("lite", "full")
"""`model.config.MODEL_NAMES`, spelled here so that `--help` does not import torch (a test keeps them equal)."""
TWO_PASS_CHOICES = ("auto", "on", "off")
"""`inference.options.TWO_PASS_CHOICES`, likewise."""


def add_network_options(parser: argparse.ArgumentParser) -> None:
    """--model and --weights: which network, with which weights."""
    parser.add_argument("--model", choices=MODEL_NAMES, default="lite", help="network [lite]")
    parser.add_argument("--weights", type=Path, help="weights file or checkpoint [the bundled model/weights/MODEL.pt]")


def add_iterations_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--iters",
        type=int,
        nargs="+",
        metavar="N",
        help="ARM iterations: N at 1/4 resolution, or N16 N8 N4 for the three stages [the model's]",
    )


def add_model_options(parser: argparse.ArgumentParser) -> None:
    """--model, --weights, --device and the inference knobs: shared by eval and predict."""
    add_network_options(parser)
    parser.add_argument("--device", default="auto", help="auto (cuda if available), cpu, cuda, cuda:N [auto]")
    parser.add_argument(
        "--backend",
        choices=["auto", "torch", "openvino"],
        default="auto",
        help="auto: $CRESTEREO_BACKEND if set, else OpenVINO on a CPU where `crestereo-pp prepare` has exported "
        "its graphs (2-3x faster), torch elsewhere; openvino: exports any graph missing first (a minute or two) [auto]",
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
    add_iterations_option(parser)
    parser.add_argument(
        "--scale",
        type=float,
        default=1.0,
        help="run the network on the pair resized by this factor in (0, 1] (faster; maps at full size) [1]",
    )
    parser.add_argument(
        "--flip",
        action="store_true",
        help="also compute the pair upside down and merge the two answers: about twice the time, fewer errors",
    )
    parser.add_argument(
        "--blend-sgbm",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="average the answer with OpenCV's SGBM where the two agree within 4 px: fewer errors for about 5 %% "
        "more time [on]",
    )
    parser.add_argument(
        "--refine-edges",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="refine the answer at its edges: its depth edges put where the left image's colour edges are (a "
        "colour-weighted median near them), and the strip along the image's left edge whose matches fall outside "
        "the right image raised towards the surface beside it: fewer errors at the edges of objects and of the "
        "image for under 10 %% more time; --no-blend-sgbm --no-refine-edges give the network's own answer [on]",
    )
    parser.add_argument(
        "--align-rows",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="where the right image's rows are off the left's by a quarter pixel or more (measured on the pair "
        "from tracked corners), resample it onto them first: about 20 ms a pair; a residual misrectification "
        "of 1 px doubles the network's errors [on]",
    )


def inference_options(args: argparse.Namespace) -> InferenceOptions:
    """--iters, --two-pass, --scale, --flip, --blend-sgbm, --refine-edges, --align-rows (and
    --raw-uncertainty where the command has it) as one value, read by `InferenceOptions` as the
    service reads its query; ValueError where they are invalid (a usage error: `main` exits 2)."""
    from crestereo_pp.inference import InferenceOptions

    return InferenceOptions(
        args.iters,
        args.two_pass,
        args.scale,
        getattr(args, "raw_uncertainty", False),
        args.flip,
        args.blend_sgbm,
        args.refine_edges,
        args.align_rows,
    )


def graphs_needed(args: argparse.Namespace) -> list[tuple[Iterations, bool]]:
    """The (iterations, warm start) of the forwards the command runs: cold at --iters; warm at
    --iters unless --two-pass off (the second of two passes starts warm); with --sequence, warm
    at --warm-iters too (the frames after the first)."""
    from crestereo_pp.inference import parse_iterations

    options = inference_options(args)
    graphs: list[tuple[Iterations, bool]] = [(options.iters, False)]
    if options.two_pass is not False:
        graphs.append((options.iters, True))
    if getattr(args, "sequence", False):
        warm_iters = parse_iterations(args.warm_iters)
        graphs.append((options.iters if warm_iters is None else warm_iters, True))
    return graphs


def load_predictor(args: argparse.Namespace) -> StereoPredictor:
    """The predictor that --model, --weights, --device, --backend and --precision name. Left to
    pick (auto), it takes OpenVINO only where the graphs of the command's forwards are in the
    cache already, else torch: a one-off command never waits for an export. Asked for OpenVINO
    (--backend openvino, or $CRESTEREO_BACKEND), it exports the missing graphs first, saying so."""
    from crestereo_pp.inference import load_model
    from crestereo_pp.inference.device import resolve_device

    graphs = graphs_needed(args)  # invalid options are an error before anything loads
    device = resolve_device(args.device, 0)

    def load(backend: BackendChoice) -> StereoPredictor:  # one call site: a warning about the weights shows once
        return load_model(args.model, args.weights, device, backend=backend, precision=args.precision)

    predictor = load(args.backend)
    if predictor.backend == "torch" or all(predictor.ready(iters, warm_start=warm) for iters, warm in graphs):
        return predictor
    if not asked_for_openvino(args.backend):
        print(
            "crestereo-pp: computing on torch: OpenVINO's graphs for these iterations are not in the cache "
            "(`crestereo-pp prepare` exports them, once per weights)",
            file=sys.stderr,
        )
        return load("torch")
    assert predictor.openvino is not None  # not torch, so OpenVINO
    counts = [c for iters, warm in graphs for c in predictor.graph_iterations(iters, warm)]  # a repeat is exported once
    print(
        f"crestereo-pp: exporting {args.model}'s OpenVINO graphs, once per weights (a minute or two; "
        "`crestereo-pp prepare` does it ahead)",
        file=sys.stderr,
    )
    if not predictor.openvino.prepare(counts, wait=True):  # side by side
        print("crestereo-pp: the OpenVINO export failed (see the log); running on torch", file=sys.stderr)
    return predictor


def asked_for_openvino(backend: BackendChoice) -> bool:
    """Whether the user named OpenVINO: --backend openvino, or --backend auto with
    $CRESTEREO_BACKEND=openvino (rather than auto choosing it; `requested_backend`)."""
    from crestereo_pp.inference.backend_choice import requested_backend

    return requested_backend(backend) == "openvino"
