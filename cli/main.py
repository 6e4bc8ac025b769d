"""`crestereo-pp`: train, evaluate, predict and export from the command line."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from . import calibrate, evaluate, export, predict, serve, train


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="crestereo-pp",
        description="CREStereo++ / Lite-CREStereo++ stereo disparity: serve, predict, train, eval, export, calibrate.",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in (serve, predict, train, evaluate, export, calibrate):
        command.add_parser(commands)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command; returns the process exit status (2 with a one-line message on bad input:
    unreadable or missing files, invalid values)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        code: int = args.run(args)
        return code
    except (ValueError, OSError) as error:
        print(f"{parser.prog} {args.command}: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
