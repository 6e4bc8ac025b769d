"""The benchmark's command line: the options, the scenario run, the tables printed and the JSON
file written; exit status 1 when any answer was unexpected."""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path

from . import __doc__ as USAGE
from .payloads import DEFAULT_DATA
from .report import memory_table, outcome_table
from .scenarios import run_bodies, run_mixed


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python bench/mixed_load", description=USAGE, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--url", required=True, help="the service, e.g. http://127.0.0.1:8000")
    parser.add_argument("--pid", type=int, required=True, help="the server's process id (its RSS is sampled)")
    parser.add_argument("--scenario", choices=("mixed", "bodies"), default="mixed")
    parser.add_argument("--clients", type=int, default=24)
    parser.add_argument("--seconds", type=float, default=300.0)
    parser.add_argument("--sample-s", type=float, default=5.0)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folders of left.png/right.png pairs")
    parser.add_argument("--variants", type=int, default=48, help="distinct crop/rescale sizes")
    parser.add_argument("--calibrations", type=int, default=4, help="cameras of each raw kind")
    parser.add_argument("--bodies", type=int, default=48)
    parser.add_argument("--rounds", type=int, default=1, help="bodies each client sends, back to back")
    parser.add_argument("--body-mib", type=float, default=31.9)
    parser.add_argument("--timeout-s", type=float, default=300.0, help="client timeout per request")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, help="write every sample and answer here")
    args = parser.parse_args(argv)
    if not Path(f"/proc/{args.pid}").is_dir():
        parser.error(f"no process {args.pid}")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    outcomes, samples = (run_mixed if args.scenario == "mixed" else run_bodies)(args)
    print()
    print(memory_table(samples))
    print()
    print(outcome_table(outcomes))
    if args.json is not None:
        record = {
            "args": {k: str(v) for k, v in vars(args).items()},
            "samples": [asdict(s) for s in samples],
            "outcomes": [asdict(o) for o in outcomes],
        }
        args.json.write_text(json.dumps(record, indent=1))
    return 1 if any(o.verdict == "unexpected" for o in outcomes) else 0
