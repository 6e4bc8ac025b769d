"""`crestereo-pp export`: checkpoint -> weights file for `load_model(weights=...)`."""

from __future__ import annotations

import argparse
from pathlib import Path

from training.export import export_weights


def add_parser(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "export",
        help="write a weights file from a training checkpoint",
        description="Write {model, config, training metadata} from a checkpoint, without optimiser state.",
    )
    parser.add_argument("checkpoint", type=Path, help="checkpoint.pt written by `crestereo-pp train`")
    parser.add_argument(
        "-o", "--output", type=Path, required=True, help="weights file to write, e.g. model/weights/lite.pt"
    )
    parser.add_argument("--fp16", action="store_true", help="store float16 tensors (half the size)")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    payload = export_weights(args.checkpoint, args.output, half=args.fp16)
    size_mib = args.output.stat().st_size / 2**20
    print(f"wrote {args.output} ({size_mib:.2f} MiB, {payload['dtype']}, step {payload['step']})")
    return 0
