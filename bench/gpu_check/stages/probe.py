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
from typing import Any

from ..plans import Plan, StageResult
from ..recipe import recipe_of, weights_for


def probe_stage(plan: Plan, deadline: float, args: argparse.Namespace, save: Callable[..., None]) -> StageResult:
    """Training throughput: bench/train_speed.py's probe rows for each model, in one process; a row
    that fails (out of memory, a compile error) is recorded and the next runs."""
    import torch
    from train_speed import measure, probe_rows

    device = torch.device(plan.device)
    on_cuda = device.type == "cuda"
    data: dict[str, Any] = {"device": torch.cuda.get_device_name(device) if on_cuda else "CPU", "rows": []}
    scratch = Path(tempfile.mkdtemp(prefix="probe-"))
    for model in plan.throughput_models:
        weights = weights_for(model, args)
        recipe = replace(recipe_of(model, plan, args), out_dir=str(scratch), val_data=None)
        rows = probe_rows(
            recipe.batch_size, recipe.lr, plan.throughput_factors, options=model == "lite", compiled=on_cuda
        )
        last_seconds, last_batch = 0.0, 1  # the wall time of the model's previous row, and its batch
        for row in rows:
            entry: dict[str, Any] = {"model": model, "row": row.name, "setting": row.description}
            entry["overrides"] = row.overrides
            expected = max(plan.throughput_row_seconds, last_seconds * row.overrides["batch_size"] / last_batch)
            started = time.monotonic()
            if deadline - started < expected + 5:
                entry["skipped"] = "no time left"
            else:
                try:
                    entry |= measure(
                        replace(recipe, **row.overrides),
                        weights,
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
                last_seconds, last_batch = time.monotonic() - started, row.overrides["batch_size"]
            print(json.dumps(entry), flush=True)
            data["rows"].append(entry)
            save(StageResult("passed", f"{len(data['rows'])} rows", data=data))  # kept if the stage is killed
    measured = [row for row in data["rows"] if "skipped" not in row]
    status = "passed" if measured else "failed"
    return StageResult(status, f"{len(measured)} of {len(data['rows'])} rows measured", data=data)
