"""The training loop: `train(config)` on one process, or one process per device under torchrun."""

from __future__ import annotations

import datetime as dt
import random
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import torch
from torch.nn.parallel import DistributedDataParallel
from tqdm import tqdm

from crestereo_pp.evaluation.evaluate import evaluate
from crestereo_pp.inference import NETWORK_ONLY, InferenceOptions, StereoPredictor
from crestereo_pp.inference.device import resolve_device
from crestereo_pp.inference.torch_backend import autocast_bf16
from crestereo_pp.inference.two_pass import half_resolution_start
from crestereo_pp.model import CREStereoPP, ModelConfig, NetworkOutput
from crestereo_pp.model.network import finest_stage_only
from crestereo_pp.model.weights import WeightsFile, load_state, model_config_of, read_weights, write_weights
from crestereo_pp.stereo_data.readers import open_dataset

from .checkpoint import restore_rng_state, rng_state
from .config import Switch, TrainConfig
from .data import TrainingBatch, TrainingData
from .distributed import DistributedContext
from .history import RunRecord, TrainingHistory
from .loss import matching_loss, sequence_loss
from .records import CsvLog, plot_curves, read_csv
from .schedule import build_scheduler, set_horizon
from .weight_average import WeightAverage

CHECKPOINT_NAME = "checkpoint.pt"
STABLE_NAME = "stable.pt"
"""A flat-decay run's checkpoint at the step where its decay begins (warmup-stable-decay): the next
run resumes from it and goes on at the peak lr, instead of restarting from the decayed weights."""
LOG_COLUMNS = ("step", "pairs_seen", "minutes", "loss", "train_epe", "lr", "pairs_per_second")
"""Columns of log.csv: loss and train_epe (px, final prediction) are means over the steps since
the previous row and over all processes; minutes is the cumulative wall time of every run in
the weights' history; pairs_per_second counts all processes."""
VALIDATION_COLUMNS = ("step", "pairs_seen", "minutes", "epe", "bad1", "bad2", "bad3", "d1_all", "raw_epe", "raw_bad2")
"""Columns of validation.csv: the metrics are those of the served weights (the checkpoint's
"model"); raw_epe and raw_bad2 are the trained weights' own when the served ones are their moving
average (ema_decay > 0), else empty."""


@dataclass(frozen=True)
class TrainResult:
    """Where a run ended: its last `step`, the `checkpoint` saved there (by rank 0), whether it
    stopped on its time budget (`out_of_time`) rather than at max_steps, and this process's
    trained `network` (in train mode)."""

    step: int
    checkpoint: Path
    out_of_time: bool
    network: CREStereoPP


def train(
    config: TrainConfig,
    *,
    resume: Path | None = None,
    init_weights: Path | None = None,
    progress: bool = True,
) -> TrainResult:
    """Train per `config`, writing checkpoint.pt, log.csv and loss_curve.png to config.out_dir.

    resume: a checkpoint to continue exactly (weights, optimiser, scheduler, step, RNG states;
    `config` should be the checkpoint's train_config with any overrides applied).
    init_weights: a weights file or checkpoint whose weights start a fresh run (new optimiser,
    step 0); its training history is carried on.
    Under torchrun each process trains on its own batches (config.batch_size each) and
    DistributedDataParallel averages the gradients; only rank 0 writes files.
    """
    if resume is not None and init_weights is not None:
        raise ValueError("give either resume or init_weights, not both")
    context = DistributedContext.from_environment()
    device = resolve_device(config.device, context.local_rank)
    context.start(device)
    try:
        return Trainer(config, context, device, resume, init_weights).run(progress)
    finally:
        context.stop()


class Trainer:
    """One process's training state: network, optimiser, schedule, history and (rank 0) logs."""

    def __init__(
        self,
        config: TrainConfig,
        context: DistributedContext,
        device: torch.device,
        resume: Path | None,
        init_weights: Path | None,
    ) -> None:
        self.config, self.context, self.device = config, context, device
        self.planned = config  # the run as configured; keep_in_time sizes self.config's end within it
        source_path = resume or init_weights
        source = read_weights(source_path, config.model) if source_path is not None else None
        self.model_config = model_config_of(source, config.model) if source else ModelConfig.preset(config.model)
        torch.manual_seed(config.seed)
        self.network = CREStereoPP(self.model_config).to(device)
        if config.channels_last:
            self.network = self.network.to(memory_format=torch.channels_last)  # type: ignore[call-overload]  # torch's stub lacks it
        self.optimizer = torch.optim.AdamW(
            self.network.parameters(),
            lr=config.lr,
            betas=config.betas,
            weight_decay=config.weight_decay,
            fused=True if is_on(config.fused_adamw, device) else None,  # None: torch's default (foreach on CUDA)
        )
        self.scheduler = build_scheduler(
            self.optimizer, config.schedule_length, config.schedule, config.warmup_fraction, config.decay_steps
        )
        self.history = TrainingHistory.from_dict(source.get("training") if source else None)
        self.start_step = 0 if source is None else self._restore(source, resumed=resume is not None)
        self.average = WeightAverage(self.network, config.ema_decay) if config.ema_decay > 0 else None
        if self.average is not None and resume is not None and source is not None and "train_model" in source:
            load_state(self.average.network, source["model"])  # "model" is the average the run kept
        if self.start_step >= config.max_steps:
            raise ValueError(f"nothing to do: the run is at step {self.start_step} and max_steps is {config.max_steps}")

        self.pairs_per_step = config.batch_size * context.world_size
        self.prior_minutes = self.history.total_minutes
        self.prior_pairs = self.history.total_pairs
        self.record = RunRecord(
            started=dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            origin="resume" if resume else "init-weights" if init_weights else "scratch",
            model=config.model,
            device=torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
            processes=context.world_size,
            first_step=self.start_step,
            last_step=self.start_step,
        )
        self.history.runs.append(self.record)
        self.out_dir = Path(config.out_dir)
        kept_rows = self.start_step if resume else None
        self.log = CsvLog(self.out_dir / "log.csv", LOG_COLUMNS, kept_rows) if context.is_main else None
        self.validation_log = (
            CsvLog(self.out_dir / "validation.csv", VALIDATION_COLUMNS, kept_rows)
            if context.is_main and config.val_data
            else None
        )
        device_ids = [device.index] if device.type == "cuda" else None
        model = DistributedDataParallel(self.network, device_ids=device_ids) if context.is_distributed else self.network
        self.model: Callable[..., NetworkOutput] = (
            torch.compile(model, mode=config.compile_mode) if config.compile else model
        )
        self.use_bf16 = config.precision == "bf16" or (config.precision == "auto" and device.type == "cuda")
        if device.type == "cuda":
            torch.backends.cudnn.benchmark = True  # the crops have one shape: pick the fastest convolutions once

    def _restore(self, source: WeightsFile, resumed: bool) -> int:
        """Start from `source`'s weights; a `resumed` checkpoint also restores the optimiser,
        schedule and random generators. Returns the step to start from."""
        trained = source.get("train_model") if resumed else None
        # a resumed run continues the trained weights, which are "train_model" when "model" is their average
        load_state(self.network, source["model"] if trained is None else trained)
        if not resumed:
            return 0
        self.optimizer.load_state_dict(source["optimizer"])
        self.scheduler.load_state_dict(source["scheduler"])
        follow_config(self.optimizer, self.scheduler, self.config)
        restore_rng_state(source["rng"])
        return int(source["step"])

    def run(self, progress: bool) -> TrainResult:
        """Train from start_step until max_steps or the time budget; log, checkpoint, return."""
        config = self.config
        bar = tqdm(
            total=config.max_steps * self.pairs_per_step,
            initial=self.start_step * self.pairs_per_step,
            unit="pair",
            desc=f"train {config.model}",
            disable=not (progress and self.context.is_main),
            dynamic_ncols=True,
        )
        run_start = window_start = time.monotonic()
        first_step_end = run_start  # when this run's first step ended (a compile, autotuning: paid once)
        window_sums = torch.zeros(2, device=self.device)  # loss and train EPE, summed over the window's steps
        window_steps = 0
        step = self.start_step
        out_of_time = False
        self.network.train()
        for batch in TrainingData(config, self.context.rank, self.device).batches(self.start_step):
            lr = self.optimizer.param_groups[0]["lr"]
            window_sums += self.train_step(batch, takes_two_passes(config, step))
            window_steps += 1
            step += 1
            bar.update(self.pairs_per_step)

            now = time.monotonic()
            if step == self.start_step + 1:
                first_step_end = now
            elif step % config.log_every == 0 and config.max_minutes is not None:
                seconds_per_step = (now - first_step_end) / (step - self.start_step - 1)
                self.keep_in_time(step, seconds_per_step, 60.0 * config.max_minutes - (now - run_start))
                config = self.config
                bar.total = config.max_steps * self.pairs_per_step
            run_minutes = (now - run_start) / 60.0
            out_of_time = self.context.any(
                config.max_minutes is not None and run_minutes >= config.max_minutes, self.device
            )
            finished = out_of_time or step == config.max_steps
            if step % config.log_every == 0 or finished:
                mean_loss, mean_epe = (self.context.mean(window_sums) / window_steps).tolist()
                rate = window_steps * self.pairs_per_step / max(time.monotonic() - window_start, 1e-9)
                bar.set_postfix(loss=f"{mean_loss:.3f}", epe=f"{mean_epe:.2f}", lr=f"{lr:.2e}")
                if self.log is not None:
                    self.log.append(
                        dict(
                            step=step,
                            pairs_seen=self.prior_pairs + self.run_pairs(step),
                            minutes=self.prior_minutes + run_minutes,
                            loss=mean_loss,
                            train_epe=mean_epe,
                            lr=lr,
                            pairs_per_second=rate,
                        )
                    )
                self.record.final_loss = mean_loss
                window_sums.zero_()
                window_steps = 0
                window_start = time.monotonic()
            if (step % config.checkpoint_every == 0 or finished) and self.context.is_main:
                self.save(step, run_minutes)
            if step == self.decay_start and not finished and self.context.is_main:
                write_weights(self.checkpoint(step, run_minutes), self.out_dir / STABLE_NAME)
            if finished:
                break
        bar.close()
        return TrainResult(step, self.out_dir / CHECKPOINT_NAME, out_of_time, self.network)

    def keep_in_time(self, step: int, seconds_per_step: float, seconds_left: float) -> None:
        """Size a flat-decay run that should end decayed (its schedule ends at max_steps) to its time
        budget (max_minutes): while at its peak lr, at each log row, its end becomes the last step
        that fits `seconds_left` at `seconds_per_step`, never past the planned end. The decay keeps
        its planned share of the run (or takes every step that fits, where fewer) and begins where
        the stable branch is then written. A run sized by a step rate it does not reach
        (validations, another GPU) so still ends decayed instead of being cut at its peak lr, and
        one whose first steps ran slow (warm-up, a busy machine) takes back the steps it can.
        All processes take the same end (the mean of their estimates)."""
        planned, config = self.planned, self.config
        decay_start = self.decay_start
        if decay_start is None or step >= decay_start or planned.schedule_length != planned.max_steps:
            return
        estimate = torch.tensor([seconds_left / max(seconds_per_step, 1e-9)], device=self.device)
        steps_that_fit = int(self.context.mean(estimate).item())
        end = min(planned.max_steps, step + max(1, steps_that_fit))
        if end == config.max_steps:
            return
        # the decay's share of the run as planned, of the run as it now ends (at most all that is left)
        share = planned.decay_steps / (planned.max_steps - self.start_step)
        decay_steps = max(1, min(end - step, round(share * (end - self.start_step))))
        self.config = replace(config, max_steps=end, schedule_steps=end, decay_steps=decay_steps)
        set_horizon(self.scheduler, end, config.schedule, config.warmup_fraction, decay_steps)
        if self.context.is_main:
            tqdm.write(
                f"train: {seconds_per_step:.3f} s per step leaves time for {steps_that_fit} more steps: "
                f"the run now ends at step {end}, its decay begins at step {end - decay_steps}"
            )

    @property
    def decay_start(self) -> int | None:
        """The step where a flat-decay schedule leaves its peak lr (None for other schedules)."""
        config = self.config
        if config.schedule != "flat-decay" or config.decay_steps >= config.schedule_length:
            return None
        return config.schedule_length - config.decay_steps

    def run_pairs(self, step: int) -> int:
        """Training pairs this run has seen when its step counter is at `step` (all processes)."""
        return (step - self.start_step) * self.pairs_per_step

    def train_step(self, batch: TrainingBatch, two_pass: bool = False) -> torch.Tensor:
        """One optimiser step on `batch`: one pass, or (`two_pass`) the full-resolution refinement
        from the network's own half-resolution disparity, as two-pass inference computes a pair.
        Returns (loss, train EPE in px), detached, on the device."""
        config = self.config
        if config.channels_last:
            batch = batch.channels_last()
        with autocast_bf16(self.device, self.use_bf16):
            init = None
            if two_pass:
                with torch.no_grad():
                    init = half_resolution_start(
                        batch.left,
                        batch.right,
                        lambda left, right: self.model(left, right, iters=config.train_iters).disparity.float(),
                    )
            # the second of two passes refines at 1/4 only
            iters = (
                config.train_iters if init is None else finest_stage_only(config.train_iters or self.model_config.iters)
            )
            output = self.model(batch.left, batch.right, iters=iters, init_disparity=init)
        predictions = [[p.float() for p in stage] for stage in output.predictions]
        loss = sequence_loss(predictions, batch.disparity, batch.valid, config.gamma, config.loss_max_disparity)
        if config.matching_weight > 0:
            assert output.features is not None  # the model is in training mode
            left_features, right_features = (f.float() for f in output.features)
            loss = loss + config.matching_weight * matching_loss(
                left_features, right_features, batch.disparity, batch.valid, config.scene_max_disparity
            )
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()  # type: ignore[no-untyped-call]  # torch leaves it unannotated
        if config.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(self.network.parameters(), config.grad_clip)
        self.optimizer.step()
        self.scheduler.step()
        if self.average is not None:
            self.average.update(self.network)
        return torch.stack([loss.detach(), end_point_error(predictions[-1][-1].detach(), batch)])

    def save(self, step: int, run_minutes: float) -> None:
        """Rank 0: validate (when configured), then write the checkpoint and the curves."""
        record = self.record
        served = self.network if self.average is None else self.average.network
        if self.validation_log is not None:
            record.validation = validate(served, self.config, self.device)
            raw: dict[str, float] = {}
            if self.average is not None:
                raw_metrics = validate(self.network, self.config, self.device)
                raw = dict(raw_epe=raw_metrics["epe"], raw_bad2=raw_metrics["bad2"])
            self.validation_log.append(
                dict(
                    step=step,
                    pairs_seen=self.prior_pairs + self.run_pairs(step),
                    minutes=self.prior_minutes + run_minutes,
                    **record.validation,
                    **raw,
                )
            )
        write_weights(self.checkpoint(step, run_minutes), self.out_dir / CHECKPOINT_NAME)
        draw_curves(self.out_dir)

    def checkpoint(self, step: int, run_minutes: float) -> WeightsFile:
        """Everything a resumed run needs at `step`: the served weights (the average, when kept),
        the trained ones, optimiser, schedule, random states and the training record so far."""
        record = self.record
        record.last_step, record.pairs, record.minutes = step, self.run_pairs(step), run_minutes
        served = self.network if self.average is None else self.average.network
        checkpoint = WeightsFile(
            model=served.state_dict(),
            config=self.model_config.to_dict(),
            model_name=self.config.model,
            train_config=self.config.to_dict(),
            optimizer=self.optimizer.state_dict(),
            scheduler=self.scheduler.state_dict(),
            step=step,
            rng=rng_state(),
            training=self.history.to_dict(),
        )
        if self.average is not None:
            checkpoint["train_model"] = self.network.state_dict()
        return checkpoint


def follow_config(
    optimizer: torch.optim.Optimizer, scheduler: torch.optim.lr_scheduler.LambdaLR, config: TrainConfig
) -> None:
    """After loading an optimiser and scheduler state saved under another config, apply this
    config's lr, betas and weight decay (so that e.g. `--resume ... --lr 1e-4` takes effect)."""
    scheduler.base_lrs = [config.lr] * len(optimizer.param_groups)
    factor = scheduler.lr_lambdas[0](scheduler.last_epoch)
    for group in optimizer.param_groups:
        group.update(initial_lr=config.lr, lr=config.lr * factor, betas=config.betas, weight_decay=config.weight_decay)


def is_on(switch: Switch, device: torch.device) -> bool:
    """An "auto" | "on" | "off" option: "auto" is on for CUDA devices only."""
    return switch == "on" or (switch == "auto" and device.type == "cuda")


def end_point_error(disparity: torch.Tensor, batch: TrainingBatch) -> torch.Tensor:
    """Mean |disparity - ground truth| (px) over the batch's valid pixels; disparity (B,1,H,W)."""
    errors = torch.where(batch.valid, (disparity - batch.disparity).abs(), 0.0)
    return errors.sum() / batch.valid.sum().clamp(min=1)


def takes_two_passes(config: TrainConfig, step: int) -> bool:
    """Whether the optimiser step after `step` (counted across resumes) is a two-pass one: a draw
    with probability ``config.two_pass_fraction`` seeded by the run's seed and the step, so that a
    resumed run repeats the uninterrupted one."""
    return config.two_pass_fraction > 0 and random.Random(f"{config.seed}:{step}").random() < config.two_pass_fraction


def validate(network: CREStereoPP, config: TrainConfig, device: torch.device) -> dict[str, float]:
    """Mean EPE, bad-1/2/3 and D1-all of `network` on config.val_data, each pair in one pass (the
    network itself, comparable along the learning curve: no host refinement (SGBM, edges); ``two_pass="auto"`` is
    a serving policy whose threshold is measured for finished weights); leaves it in train mode."""
    if config.val_data is None:
        raise ValueError("validation needs config.val_data")
    predictor = StereoPredictor(network, config.model, None, device)
    report = evaluate(
        open_dataset(config.val_data),
        predictor,
        dataset_name=config.val_data,
        options=InferenceOptions(two_pass=False, **NETWORK_ONLY),
        progress=False,
    )
    network.train()
    metrics = report.mean(config.model).metrics
    return dict(epe=metrics.epe, bad1=metrics.bad1, bad2=metrics.bad2, bad3=metrics.bad3, d1_all=metrics.d1_all)


def draw_curves(out_dir: Path) -> None:
    """loss_curve.png from log.csv (loss and train EPE against step); validation_curve.png from
    validation.csv (dev bad-2 % and EPE against cumulative training minutes) when validation ran."""
    rows = read_csv(out_dir / "log.csv")
    steps = [int(r["step"]) for r in rows]
    series = {
        name: (steps, [float(r[column]) for r in rows])
        for name, column in (("loss", "loss"), ("train EPE px", "train_epe"))
    }
    plot_curves(series, out_dir / "loss_curve.png", "step", "loss / EPE (px), log scale", log_y=True)
    validation = read_csv(out_dir / "validation.csv")
    if validation:
        minutes = [float(r["minutes"]) for r in validation]
        validation_series = {
            name: (minutes, [float(r[column]) for r in validation])
            for name, column in (("dev bad-2 %", "bad2"), ("dev EPE px", "epe"))
        }
        plot_curves(validation_series, out_dir / "validation_curve.png", "cumulative training minutes", "dev metric")
