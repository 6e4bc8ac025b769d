"""The probe stage: the training step's throughput per model and setting (bench/train_speed.py's
`probe_rows`, each timed by its `measure`)."""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..plans import Plan, StageResult
from ..recipe import recipe_of, weights_for

if TYPE_CHECKING:
    from train_speed import ProbeRow

    from crestereo_pp.model.config import ModelName


def probe_stage(plan: Plan, deadline: float, args: argparse.Namespace, save: Callable[..., None]) -> StageResult:
    """Training throughput: bench/train_speed.py's probe rows for each model, in one process; a row
    that fails (out of memory, a compile error) is recorded and the next runs. Every model's eager
    rows come first and the compiled ones last (`probe_order`): a compile can take minutes, and
    then it takes only the time the other rows leave. The rows train into a scratch folder, removed
    at the end."""
    with tempfile.TemporaryDirectory(prefix="probe-") as scratch:
        return probe_rows_in(Path(scratch), plan, deadline, args, save)


def probe_rows_in(
    scratch: Path, plan: Plan, deadline: float, args: argparse.Namespace, save: Callable[..., None]
) -> StageResult:
    """`probe_stage` with its training runs writing into `scratch`."""
    import torch
    from train_speed import measure

    device = torch.device(plan.device)
    on_cuda = device.type == "cuda"
    data: dict[str, Any] = {"device": torch.cuda.get_device_name(device) if on_cuda else "CPU", "rows": []}
    recipes = {
        model: replace(recipe_of(model, plan, args), out_dir=str(scratch), val_data=None)
        for model in plan.throughput_models
    }
    # each model's previous row: its wall time and batch (a larger batch is expected to take longer)
    last: dict[ModelName, tuple[float, int]] = {model: (0.0, 1) for model in recipes}
    for model, row in probe_order(plan, recipes, compiled=on_cuda):
        entry: dict[str, Any] = {"model": model, "row": row.name, "setting": row.description}
        entry["overrides"] = row.overrides
        last_seconds, last_batch = last[model]
        expected = max(plan.throughput_row_seconds, last_seconds * row.overrides["batch_size"] / last_batch)
        started = time.monotonic()
        if deadline - started < expected + 5:
            entry["skipped"] = "no time left"
        else:
            try:
                entry |= measure(
                    replace(recipes[model], **row.overrides),
                    weights_for(model, args),
                    device,
                    plan.throughput_steps,
                    max_seconds=plan.throughput_row_seconds,
                    warmup_steps=plan.throughput_warmup,
                )
            except Exception as error:  # out of memory, a compile failure: the next row still runs
                entry["skipped"] = f"{type(error).__name__}: {str(error)[:160]}"
            finally:
                torch._dynamo.reset()
                if on_cuda:
                    torch.cuda.empty_cache()
            last[model] = (time.monotonic() - started, row.overrides["batch_size"])
        print(json.dumps(entry), flush=True)
        data["rows"].append(entry)
        save(StageResult("passed", f"{len(data['rows'])} rows", data=data))  # kept if the stage is killed
    measured = [row for row in data["rows"] if "skipped" not in row]
    status = "passed" if measured else "failed"
    return StageResult(status, f"{len(measured)} of {len(data['rows'])} rows measured", data=data)


def probe_order(plan: Plan, recipes: dict[ModelName, Any], compiled: bool) -> list[tuple[ModelName, ProbeRow]]:
    """The probe's (model, row) pairs in the order they run: bench/train_speed.py's `probe_rows`
    around each model's recipe (the options for lite only), every model's eager rows before any
    compiled row."""
    from train_speed import probe_rows

    rows = [
        (model, row)
        for model, recipe in recipes.items()
        for row in probe_rows(
            recipe.batch_size, recipe.lr, plan.throughput_factors, options=model == "lite", compiled=compiled
        )
    ]
    return sorted(rows, key=lambda pair: bool(pair[1].overrides.get("compile")))
