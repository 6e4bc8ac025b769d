"""`crestereo-pp prepare`: export a model's OpenVINO graphs into the cache, once per weights."""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING

from .options import add_iterations_option, add_network_options

if TYPE_CHECKING:
    from crestereo_pp.inference.options import StageCounts


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Export the OpenVINO graphs of MODEL at --iters, for cold and warm starts (two passes and the frames "
        "of a sequence start warm), into the cache ($CRESTEREO_CACHE_DIR, else $XDG_CACHE_HOME/crestereo-pp, "
        "else ~/.cache/crestereo-pp), where predict, eval, the service and the Python API read them: until "
        "then they compute on torch, 2-3x slower on a CPU. Each graph takes a minute or two of one core (they are "
        "exported side by side), once per weights "
        "and iterations; a graph already in the cache is not exported again."
    )
    add_network_options(parser)
    add_iterations_option(parser)
    parser.add_argument(
        "--prune",
        action="store_true",
        help="also remove the cache's graph folders of other torch or export versions, which this install never "
        "reads (an update leaves them behind); those of other weights are kept",
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Exit status 1 where an export failed (those calls run on torch)."""
    from crestereo_pp.inference import load_model, parse_iterations

    iters = parse_iterations(args.iters)
    predictor = load_model(args.model, args.weights, "cpu", backend="openvino")
    openvino = predictor.openvino
    assert openvino is not None  # asked for by name: ValueError where it cannot run
    uses: dict[StageCounts, str] = {}  # every graph of cold and warm starts, two passes included
    for counts, use in zip(
        predictor.graph_iterations(iters, warm_start=True),
        ("cold starts and a sequence's warm frames", "the second of two passes"),
        strict=True,
    ):
        uses[counts] = f"{uses[counts]}, and {use}" if counts in uses else use
    missing = [counts for counts in uses if not openvino.ready(counts)]
    for counts in uses:
        if counts not in missing:
            print(f"{args.model}'s graph for iterations {counts} ({uses[counts]}): in the cache already")
    if missing:
        graphs = " and ".join(f"iterations {counts} ({uses[counts]})" for counts in missing)
        print(f"exporting {args.model}'s graphs for {graphs}, side by side...", flush=True)
        start = time.monotonic()
        predictor.prepare(iters, warm_start=True)
        for counts in missing:
            print(f"{args.model}'s graph for iterations {counts}: {'ready' if openvino.ready(counts) else 'failed'}")
        print(f"exported in {time.monotonic() - start:.0f} s")
    print(f"cache: {openvino.graph_dir or 'none (weights without a hash: in memory only)'}")
    _other_versions(prune=args.prune)
    return 0 if predictor.ready(iters, warm_start=True) else 1


def _other_versions(*, prune: bool) -> None:
    """Say how much the graphs of other versions take, and remove them where asked."""
    from crestereo_pp.inference.openvino_backend import other_version_graph_folders

    folders = other_version_graph_folders()
    if not folders:
        return
    megabytes = sum(_bytes(folder) for folder in folders) / 1e6
    what = f"{len(folders)} graph folder{'s' if len(folders) > 1 else ''} of other torch or export versions"
    if prune:
        for folder in folders:
            shutil.rmtree(folder, ignore_errors=True)
        print(f"removed {what} ({megabytes:.0f} MB)")
    else:
        print(f"{what} in the cache, which this install does not read ({megabytes:.0f} MB): --prune removes them")


def _bytes(folder: Path) -> int:
    """The bytes of the files under `folder`; files removed meanwhile count nothing."""
    total = 0
    for path in folder.rglob("*"):
        try:
            total += path.stat().st_size if path.is_file() else 0
        except FileNotFoundError:
            pass
    return total
