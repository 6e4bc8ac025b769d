"""The arms stage: how a data candidate is measured before it is adopted. Two training runs of
equal pairs from the same weights: the recipe (control) and the recipe with the --arm settings
(candidate), each scored with the default inference on the dev pairs (the Middlebury 2014 pairs
also apart) and on procedural scenes drawn as the candidate trains."""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from ..plans import Plan, StageResult
from .train import Start, returned_weights, run_rate, size_run, sized_config, stage_recipe, starting_point

ARMS = ("control", "candidate")
APART_PREFIX = "middlebury2014"
"""The dev pairs also scored apart: the cluttered rooms (thin structures, wide ranges, weakly
textured planes) that lite loses to SGBM on."""


def arms_stage(plan: Plan, deadline: float, args: argparse.Namespace, save: Callable[..., None]) -> StageResult:
    """Train both arms of --model for the same steps (sized by the slower arm's step rate to fit
    both in the time left, less plan.arm_score_seconds each for scoring them) from `starting_point`,
    each into a scratch folder; return each arm's checkpoint as arm-NAME.pt and its scores."""
    if not args.arm:
        return StageResult("skipped", "no candidate: give its settings with --arm KEY=VALUE")
    try:
        start = starting_point(args)
    except ValueError as error:
        return StageResult("failed", str(error))
    recipe, adopted = stage_recipe(plan, args, deadline, runs=len(ARMS))
    configs, rates, first_steps = {}, {}, {}
    # The control is the adopted row itself; the candidate's data may cost more: its rate is measured.
    for name, config, row in zip(ARMS, (recipe, replace(recipe, **dict(args.arm))), (adopted, None), strict=True):
        configs[name], rates[name], first_steps[name] = run_rate(config, start, plan, row)
    scoring = len(ARMS) * plan.arm_score_seconds
    seconds = (deadline - time.monotonic() - plan.train_tail_seconds - scoring) / len(ARMS)
    # Each arm's run compiles again where the setting compiles: the adopted row's first step, in both.
    size = size_run(min(rates.values()), seconds - max(first_steps.values()), plan, recipe.ema_decay)
    family = family_scenes(configs["candidate"], plan)
    print(f"arms: {size.steps} steps each from {start.path} (step {start.first_step}); rates {rates}", flush=True)
    rows = []
    for name, config in configs.items():
        with tempfile.TemporaryDirectory(prefix=f"arm-{name}-") as scratch:  # only the checkpoints are returned
            sized = sized_config(config, Path(scratch), start, size, seconds, None)
            rows.append(train_arm(name, sized, start, args, plan, family))
        save(StageResult("running", f"{name} done", data=dict(rows=rows)))
    data: dict[str, Any] = dict(
        model=args.model,
        weights=str(start.path),
        adopted=None if adopted is None else adopted["row"],
        arm={key: value for key, value in args.arm},
        steps=size.steps,
        pairs=size.steps * recipe.batch_size,
        steps_per_s={name: round(rate, 2) for name, rate in rates.items()},
        family="{} procedural scenes drawn as the candidate trains, {}x{}".format(len(family), *plan.arm_scene_size),
        rows=rows,
    )
    print(json.dumps(data), flush=True)
    detail = "; ".join(f"{row['arm']}: dev bad-2 {row.get('dev_bad2', '-')}" for row in rows)
    return StageResult("passed", f"{size.steps} steps each; {detail}", data=data)


def family_scenes(candidate: Any, plan: Plan) -> list[Any]:
    """plan.arm_scenes procedural scenes drawn as `candidate` (a TrainConfig) draws its crops, at
    plan.arm_scene_size with the disparities scaled to that width, from `--procedural`'s seeds."""
    from crestereo_pp.cli.evaluate import PROCEDURAL_SEED  # what `crestereo-pp eval --procedural` draws
    from crestereo_pp.stereo_data.synthetic import SceneGenerator

    height, width = plan.arm_scene_size
    scenes = candidate.scene_config
    config = replace(
        scenes,
        height=height,
        width=width,
        max_disparity=scenes.max_disparity * width / scenes.width,
        wide_max_disparity=scenes.wide_max_disparity * width / scenes.width,  # resolved by SceneConfig
    )
    return SceneGenerator(config).samples(plan.arm_scenes, PROCEDURAL_SEED)


def train_arm(
    name: str, config: Any, start: Start, args: argparse.Namespace, plan: Plan, family: Sequence[Any]
) -> dict[str, Any]:
    """Train one arm, return its checkpoint as --out/arm-NAME.pt (the decayed end, to serve) and
    its stable branch as --out/arm-NAME-stable.pt (to resume, as a train stage's stable.pt), and
    score it: mean EPE, bad-1 and bad-2 with the default inference on the dev pairs (all;
    APART_PREFIX's apart) and on the `family` scenes."""
    from crestereo_pp.training.trainer import STABLE_NAME, train

    began = time.monotonic()
    result = train(config, **start.source, progress=False)
    returned = args.out / f"arm-{name}.pt"
    shutil.copyfile(result.checkpoint, returned)
    stable = Path(config.out_dir) / STABLE_NAME
    if stable.is_file():
        shutil.copyfile(stable, args.out / f"arm-{name}-stable.pt")
    compacted = [path.name for path in (returned, args.out / f"arm-{name}-stable.pt") if returned_weights(path)]
    row: dict[str, Any] = dict(
        arm=name,
        settings={key: getattr(config, key) for key, _ in args.arm},
        steps=result.step - start.first_step,
        train_s=round(time.monotonic() - began, 1),
        weights_only_fp16=compacted,
    )
    predictor = arm_predictor(returned, args.model, plan)
    if args.data is not None:
        from crestereo_pp.stereo_data.readers import open_dataset

        dataset = open_dataset(args.data)
        pairs = [dataset[i] for i in range(len(dataset))]
        row.update(scores("dev", pairs, predictor))
        row.update(scores("apart", [pair for pair in pairs if pair.name.startswith(APART_PREFIX)], predictor))
    row.update(scores("family", family, predictor))
    return row


def arm_predictor(weights: Path, model: str, plan: Plan) -> Any:
    """The arm's weights on the stage's device, in torch fp32 (no compile, no CUDA graphs): both
    arms scored alike."""
    from crestereo_pp.inference import load_model

    return load_model(model, weights, plan.device, backend="torch", precision="fp32", cuda_graphs=False)


def scores(prefix: str, samples: Sequence[Any], predictor: Any) -> dict[str, Any]:
    """{PREFIX_epe, PREFIX_bad1, PREFIX_bad2, PREFIX_pairs}: the mean over `samples` with the
    default inference, and PREFIX_bad2_each: each sample's bad-2, in order (the arms are compared
    pair by pair too); empty where there are none."""
    from crestereo_pp.evaluation.evaluate import evaluate

    if not samples:
        return {}
    report = evaluate(samples, predictor, dataset_name=prefix, progress=False)
    metrics = report.mean(predictor.name).metrics
    return {
        f"{prefix}_epe": round(metrics.epe, 3),
        f"{prefix}_bad1": round(metrics.bad1, 2),
        f"{prefix}_bad2": round(metrics.bad2, 2),
        f"{prefix}_pairs": len(samples),
        f"{prefix}_bad2_each": [round(pair.methods[predictor.name].metrics.bad2, 2) for pair in report.pairs],
    }
