"""The train stage: --model from its weights for the minutes left, in one run sized by a short
probe run's step rate to end its flat-decay schedule in time."""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..plans import MAX_FILE_BYTES, Plan, StageResult
from ..recipe import recipe_of, weights_for

if TYPE_CHECKING:
    from crestereo_pp.model.weights import WeightsFile


@dataclass(frozen=True)
class RunSize:
    """The training run that fits the time left: `steps` more steps, flat-decay over the last
    `decay_steps` of them, a validation and checkpoint every `checkpoint_every`, and the weight
    average's decay `ema_decay` (its horizon, 1 / (1 - decay) steps, a quarter of the run at most)."""

    steps: int
    decay_steps: int
    checkpoint_every: int
    ema_decay: float


def size_run(steps_per_second: float, seconds: float, plan: Plan, ema_decay: float) -> RunSize:
    """Size the run to `seconds` at the probe's `steps_per_second` (10 % kept for the validations
    along the way), at most plan.train_steps; `ema_decay` is the recipe's, shortened for short runs."""
    steps = max(1, min(plan.train_steps, int(0.9 * steps_per_second * seconds)))
    return RunSize(
        steps=steps,
        decay_steps=max(1, round(plan.decay_fraction * steps)),
        checkpoint_every=max(1, steps // 4),
        ema_decay=0.0 if ema_decay == 0 else min(ema_decay, max(0.9, 1.0 - 4.0 / steps)),
    )


def median_rate(rows: list[dict[str, str]]) -> float:
    """The median pairs/s of a training log's rows (its windows), the first (warm-up, autotuning)
    left out where there are more."""
    rates = [float(row["pairs_per_second"]) for row in rows]
    return statistics.median(rates[1:] or rates)


def adopted_row(rows: list[dict[str, Any]], model: str, seconds: float) -> dict[str, Any] | None:
    """The probe row that trains `model` on the most pairs in `seconds`: pairs/s times the seconds
    left after its first step (compilation); None without a measured row."""
    measured = [row for row in rows if row["model"] == model and "skipped" not in row]
    if not measured:
        return None
    return max(measured, key=lambda row: row["pairs_per_s"] * max(0.0, seconds - row["first_step_s"]))


@dataclass(frozen=True)
class Start:
    """Where a stage's training starts: the weights file `path` (`weights_for`), its contents
    `saved`, the keyword that `training.trainer.train` takes it by (resume where the file holds
    an optimiser state, else init_weights: a fresh optimiser from step 0) and the step it is at."""

    path: Path
    saved: WeightsFile
    source: dict[str, Path]
    first_step: int

    @property
    def resumed(self) -> bool:
        return "resume" in self.source


def starting_point(args: argparse.Namespace) -> Start:
    """The weights --model trains from (`weights_for`); ValueError where the file holds another model."""
    from crestereo_pp.model.weights import read_weights

    path = weights_for(args.model, args)
    saved = read_weights(path)
    if saved.get("model_name") != args.model:
        raise ValueError(f"{path} holds {saved.get('model_name')!r} weights, not {args.model!r}")
    if "optimizer" in saved:
        return Start(path, saved, {"resume": path}, int(saved["step"]))
    return Start(path, saved, {"init_weights": path}, 0)


def stage_recipe(
    plan: Plan, args: argparse.Namespace, deadline: float, runs: int = 1
) -> tuple[Any, dict[str, Any] | None]:
    """The TrainConfig a stage trains --model with (`recipe_of`), and with --adopt the probe
    stage's best row for `runs` runs sharing the time left (`adopted_row`: each pays its first
    step), whose settings it then holds; None where none was adopted."""
    recipe = recipe_of(args.model, plan, args)
    if not (args.adopt and args.probe_result is not None and args.probe_result.is_file()):
        return recipe, None
    probe = json.loads(args.probe_result.read_text())["data"]
    adopted = adopted_row(probe.get("rows", []), args.model, (deadline - time.monotonic()) / runs)
    if adopted is None:
        return recipe, None
    print(f"adopted the probe's row {adopted['row']} ({probe.get('device')}): {adopted['setting']}", flush=True)
    return replace(recipe, **adopted["overrides"]), adopted


def step_rate(config: Any, start: Start, plan: Plan) -> tuple[Any, float]:
    """Train plan.probe_steps steps of `config` from `start` into a scratch folder: the steps per
    second after the first window. A lent GPU is minutes long: where that fails, the same again in
    the plainest setting (fp32, plain AdamW), not never. Returns the config that ran and its rate."""
    from crestereo_pp.training.records import read_csv
    from crestereo_pp.training.trainer import train

    def rate(trial_config: Any) -> float:
        with tempfile.TemporaryDirectory(prefix="probe-") as folder:
            trial = replace(
                trial_config,
                out_dir=folder,
                max_steps=start.first_step + plan.probe_steps,
                schedule_steps=start.first_step + plan.probe_steps + 1,
                decay_steps=1,
                max_minutes=1.5,
                log_every=max(1, plan.probe_steps // 4),
                checkpoint_every=10**9,
                val_data=None,
            )
            train(trial, **start.source, progress=False)
            return median_rate(read_csv(Path(folder) / "log.csv")) / float(trial_config.batch_size)

    try:
        return config, rate(config)
    except Exception as error:
        print(f"probe failed ({type(error).__name__}: {error}); again in fp32 with plain AdamW", flush=True)
        plainest = replace(config, precision="fp32", fused_adamw="off")
        return plainest, rate(plainest)


def run_rate(config: Any, start: Start, plan: Plan, adopted: dict[str, Any] | None) -> tuple[Any, float, float]:
    """What a run of `config` is sized by: its steps per second and the seconds of its first step
    (a compile; paid inside the run). With `adopted` (the probe row whose settings `config`
    holds), that row's measured pairs/s and first step: the probe stage ran this setting on this
    GPU through the real trainer. Else `step_rate`'s own probe run (its compile paid there)."""
    if adopted is None:
        ran, steps_per_second = step_rate(config, start, plan)
        return ran, steps_per_second, 0.0
    return config, adopted["pairs_per_s"] / config.batch_size, adopted["first_step_s"]


def sized_config(config: Any, out_dir: Path, start: Start, size: RunSize, seconds: float, val_data: Any) -> Any:
    """`config` as one run of `size` from `start` into `out_dir`, within `seconds`, validating on
    `val_data` (None: no validation) at each checkpoint."""
    last_step = start.first_step + size.steps
    return replace(
        config,
        out_dir=str(out_dir),
        max_steps=last_step,
        schedule_steps=last_step,
        decay_steps=size.decay_steps,
        checkpoint_every=size.checkpoint_every,
        ema_decay=size.ema_decay,
        max_minutes=max(0.05, seconds / 60.0),
        val_data=val_data,
    )


def returned_weights(path: Path) -> bool:
    """Keep the checkpoint at `path` within the output limit: a file of MAX_FILE_BYTES or more
    (full's training state) is rewritten as float16 weights only. Whether it was."""
    from crestereo_pp.model.weights import read_weights, weights_of, write_weights

    if not path.is_file() or path.stat().st_size < MAX_FILE_BYTES:
        return False
    write_weights(weights_of(read_weights(path), half=True), path)
    return True


def train_stage(plan: Plan, deadline: float, args: argparse.Namespace, save: Callable[..., None]) -> StageResult:
    """Train --model from `weights_for` (resumed where the file holds an optimiser state) into --out:
    a probe run's step rate sizes the run (`size_run`); with --adopt, the probe stage's best row
    (`adopted_row`) sets the step, and its measured pairs/s and first step size the run without a
    probe run. Its numbers: steps, pairs/s, losses, peak memory, dev curve."""
    import torch

    from crestereo_pp.model.weights import network_from_weights, read_weights
    from crestereo_pp.training.records import read_csv
    from crestereo_pp.training.trainer import STABLE_NAME, train, validate

    try:
        start = starting_point(args)
    except ValueError as error:
        return StageResult("failed", str(error))
    recipe, adopted = stage_recipe(plan, args, deadline)
    began = time.monotonic()
    recipe, steps_per_second, first_step_s = run_rate(recipe, start, plan, adopted)
    probe_seconds = time.monotonic() - began
    seconds = deadline - time.monotonic() - plan.train_tail_seconds
    size = size_run(steps_per_second, seconds - first_step_s, plan, recipe.ema_decay)
    config = sized_config(recipe, args.out, start, size, seconds, str(args.data) if args.data is not None else None)
    print(
        f"{'probe' if adopted is None else 'adopted row'}: {steps_per_second:.2f} steps/s ({probe_seconds:.0f} s); "
        f"training {args.model} from {start.path} "
        f"(step {start.first_step}) for {size.steps} steps, at most {seconds / 60.0:.2f} min: "
        f"{json.dumps(config.to_dict())}",
        flush=True,
    )
    start_dev = None
    if config.val_data is not None:  # the starting point, as the run's validations measure it
        network = network_from_weights(start.saved, args.model).to(plan.device)
        start_dev = validate(network, config, torch.device(plan.device))
    result = train(config, **start.source, progress=False)
    rows = read_csv(args.out / "log.csv")
    compacted = [path.name for path in (result.checkpoint, args.out / STABLE_NAME) if returned_weights(path)]
    data: dict[str, Any] = dict(
        model=args.model,
        weights=str(start.path),
        adopted=None if adopted is None else adopted["row"],
        resumed=start.resumed,
        steps=result.step - start.first_step,
        planned_steps=size.steps,
        probe_steps_per_s=round(steps_per_second, 2),
        pairs_per_s_median=round(median_rate(rows), 1),
        batch_size=config.batch_size,
        crop=f"{config.crop_height}x{config.crop_width}",
        lr=config.lr,
        decay_steps=size.decay_steps,
        ema_decay=size.ema_decay,
        compile=config.compile,
        bf16=config.precision == "bf16" or (config.precision == "auto" and plan.device == "cuda"),
        final_loss=float(rows[-1]["loss"]),
        final_train_epe=float(rows[-1]["train_epe"]),
        peak_gib=round(torch.cuda.max_memory_allocated() / 2**30, 1) if plan.device == "cuda" else None,
        checkpoint_mib=round(result.checkpoint.stat().st_size / 2**20, 1),
        stable_step=read_weights(args.out / STABLE_NAME)["step"] if (args.out / STABLE_NAME).is_file() else None,
        weights_only_fp16=compacted,
    )
    if start_dev is not None:
        data["start_dev"] = {k: round(v, 3) for k, v in start_dev.items() if k in ("epe", "bad1", "bad2")}
    validation = read_csv(args.out / "validation.csv")
    if validation:
        data["dev"] = [
            {k: float(v) for k, v in row.items() if k in ("step", "epe", "bad1", "bad2")} for row in validation
        ]
    print(json.dumps(data))
    return StageResult("passed", f"{data['steps']} steps, {data['pairs_per_s_median']} pairs/s", data=data)
