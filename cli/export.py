"""`crestereo-pp export`: checkpoint -> weights file for `load_model(weights=...)`, or -> ONNX."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Write {model, config, training metadata} from a checkpoint, without optimiser state; "
        "with --onnx, an ONNX model of a fixed input size instead (network, padding and "
        "uncertainty calibration in one graph)."
    )
    parser.add_argument("checkpoint", type=Path, help="checkpoint.pt written by `crestereo-pp train`, or weights")
    parser.add_argument(
        "-o", "--output", type=Path, required=True, help="file to write, e.g. model/weights/lite.pt or lite.onnx"
    )
    parser.add_argument("--fp16", action="store_true", help="store float16 tensors (half the size)")
    onnx = parser.add_argument_group("ONNX")
    onnx.add_argument("--onnx", action="store_true", help="write an ONNX model (opset 18) instead of weights")
    onnx.add_argument("--height", type=int, help="input height in px of the ONNX model (any size)")
    onnx.add_argument("--width", type=int, help="input width in px of the ONNX model (any size)")
    onnx.add_argument("--batch", type=int, default=1, help="pairs per call of the ONNX model [1]")
    onnx.add_argument(
        "--iters",
        type=int,
        nargs="+",
        metavar="N",
        help="ARM iterations baked into the graph: N or N16 N8 N4 [the model's]",
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from crestereo_pp.training.export import export_weights

    if args.onnx:
        return run_onnx(args)
    payload = export_weights(args.checkpoint, args.output, half=args.fp16)
    size_mib = args.output.stat().st_size / 2**20
    print(f"wrote {args.output} ({size_mib:.2f} MiB, {payload['dtype']}, step {payload['step']})")
    return 0


def run_onnx(args: argparse.Namespace) -> int:
    from crestereo_pp.inference import load_model, parse_iterations
    from crestereo_pp.inference.onnx_export import export_onnx
    from crestereo_pp.model.weights import read_weights

    if args.height is None or args.width is None:
        raise ValueError("--onnx needs --height and --width (the model's fixed input size)")
    if args.fp16:
        raise ValueError("--fp16 applies to weights files, not to --onnx")
    iters = parse_iterations(args.iters)
    name = str(read_weights(args.checkpoint).get("model_name") or "lite")
    predictor = load_model(name, args.checkpoint, "cpu")
    export_onnx(predictor, args.output, args.height, args.width, args.batch, iters)
    size_mib = args.output.stat().st_size / 2**20
    print(f"wrote {args.output} ({size_mib:.2f} MiB, {name}, input {args.batch}x3x{args.height}x{args.width})")
    return 0
