"""`crestereo-pp`: serve, predict, prepare, train, evaluate, export and calibrate from the command line.

A command's module is imported only when that command is named: `--help` and argument errors
answer without loading torch, and no command needs the packages of another (`calibrate` needs
the `train` extra; the others run in the serving install that `make serve` builds).
"""

from __future__ import annotations

import argparse
import sys
import warnings
from collections.abc import Sequence
from importlib import import_module
from typing import TextIO

COMMANDS = {  # name: (module in cli/, summary in `crestereo-pp --help`)
    "serve": ("serve", "the HTTP service (configured by the CRESTEREO_* variables), here or on a Ray cluster"),
    "predict": (
        "predict",
        "disparity of one rectified pair (or a raw one with --calibration), or of folders / globs of pairs",
    ),
    "prepare": ("prepare", "export the OpenVINO graphs that predict, eval and the Python API read from the cache"),
    "train": ("train", "train a network (procedural scenes and/or datasets; torchrun for several GPUs)"),
    "eval": ("evaluate", "EPE, bad-1/2/3, D1-all and time per pair and mean, on a dataset with ground truth"),
    "export": ("export", "write a weights file (or an ONNX model) from a training checkpoint or weights file"),
    "calibrate": (
        "calibrate",
        "fit P(error > 2 px) from the uncertainty on procedural scenes; store it in the weights",
    ),
}


def build_parser(argv: Sequence[str]) -> argparse.ArgumentParser:
    """The parser of `argv`: every command listed, with the arguments of the one `argv` names."""
    parser = argparse.ArgumentParser(
        prog="crestereo-pp",
        description="CREStereo++ / Lite-CREStereo++ stereo disparity: " + ", ".join(COMMANDS) + ".",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    named = next((word for word in argv if not word.startswith("-")), None)
    for name, (module, summary) in COMMANDS.items():
        command = commands.add_parser(name, help=summary)
        if name == named:
            import_module(f"crestereo_pp.cli.{module}").add_arguments(command)
    return parser


def print_warning(
    message: Warning | str,
    category: type[Warning],
    filename: str,
    lineno: int,
    file: TextIO | None = None,
    line: str | None = None,
) -> None:
    """A Python warning as one line, without the source line that Python prints beneath it."""
    print(f"crestereo-pp: warning: {message}", file=sys.stderr)


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command; returns the process exit status (2 with a one-line message on bad input:
    unreadable or missing files, invalid values; 130 on Ctrl-C)."""
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    with warnings.catch_warnings():
        warnings.showwarning = print_warning
        try:
            code: int = args.run(args)
            return code
        except (ValueError, OSError) as error:
            print(f"{parser.prog} {args.command}: error: {error}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:  # Ctrl-C: one line, not a traceback; 130 as a shell reports it
            print(f"{parser.prog} {args.command}: interrupted", file=sys.stderr)
            return 130


if __name__ == "__main__":
    raise SystemExit(main())
