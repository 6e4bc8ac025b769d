"""Typed training configuration, its presets (the paper's two stages) and (de)serialisation."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any, Literal

from crestereo_pp.model.config import ModelName
from crestereo_pp.stereo_data.synthetic import PhotometricConfig, SceneConfig

SYNTHETIC = "synthetic"
"""The `path` of a DataSource that stands for the procedural scene generator."""

Schedule = Literal["one-cycle", "linear", "constant", "flat-decay"]
Precision = Literal["auto", "fp32", "bf16"]
Switch = Literal["auto", "on", "off"]
CompileMode = Literal["default", "reduce-overhead", "max-autotune-no-cudagraphs"]


@dataclass(frozen=True)
class DataSource:
    """One training source and its sampling weight.

    path: "synthetic" (the procedural generator) or the root of a dataset in any layout that
    `stereo_data.readers.open_dataset` reads. weight: relative probability that a training pair
    comes from this source (weights of all sources are normalised to sum to 1).
    """

    path: str
    weight: float = 1.0

    def __post_init__(self) -> None:
        if not self.weight > 0:
            raise ValueError(f"source weight must be positive, got {self.weight} for {self.path!r}")

    @classmethod
    def parse(cls, text: str) -> DataSource:
        """Parse "PATH" or "PATH=WEIGHT", e.g. "synthetic=0.7" or "/data/kitti2015=0.3"."""
        path, separator, weight = text.rpartition("=")
        if not separator:
            return cls(text)
        try:
            return cls(path, float(weight))
        except ValueError as error:
            raise ValueError(f"bad source {text!r}: expected PATH or PATH=WEIGHT ({error})") from None

    def __str__(self) -> str:
        return f"{self.path}={self.weight:g}"


def _knob(default: Any, help: str, metavar: str | None = None) -> Any:
    """A config field with its command-line help text (and the placeholder shown there)."""
    return field(default=default, metadata={"help": help, "metavar": metavar})


@dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run; every field is a `crestereo-pp train` option."""

    model: ModelName = _knob("lite", "network preset to train")
    sources: tuple[DataSource, ...] = _knob(
        (DataSource(SYNTHETIC),),
        "a training source (repeat for a mixture; replaces the default); PATH 'synthetic' is the procedural generator",
        metavar="PATH[=WEIGHT]",
    )
    crop_height: int = _knob(384, "training crop height in pixels (multiple of 32)")
    crop_width: int = _knob(512, "training crop width in pixels (multiple of 32)")
    max_disparity: float | None = _knob(
        None, "largest disparity (px) of the procedural scenes [192 * crop_width / 512]"
    )
    photo_textures: int = _knob(
        0, "procedural scenes: texture slots per scene filled with photo crops (needs scikit-image)"
    )
    texel_size: tuple[float, float] = _knob(
        SceneConfig.texel_size,
        "procedural scenes: range of the texture texel size in px before the scene's scale (log-uniform); "
        "smaller gives finer detail, and the smallest times the smallest scale must cover 1 px",
    )
    supersample: int = _knob(
        1,
        "procedural scenes: anti-aliasing, each pixel the mean of N x N samples over its area (costs N^2 in "
        "rendering); allows texels down to 1/N px",
        metavar="N",
    )
    curve_probability: float = _knob(
        0.0,
        "procedural scenes: fraction of foreground surfaces that are curved (domes, bowls, saddles, cylinders) "
        "instead of planar",
    )
    vignetting: float = _knob(
        0.0, "procedural scenes: at most this share of the light lost at the frame's corners, drawn per view"
    )
    jpeg_probability: float = _knob(
        0.0, "procedural scenes: fraction of the views saved as JPEG (quality 40-95) and read back"
    )
    lighting_probability: float = _knob(
        0.0, "procedural scenes: fraction lit by a directional light (shading by the surfaces' orientation)"
    )
    specular_probability: float = _knob(
        0.0,
        "procedural scenes: fraction of the surfaces of lit scenes with highlights, which differ between the views",
    )
    road_probability: float = _knob(
        0.0,
        "procedural scenes: fraction laid out as a road scene (a ground plane receding to a horizon under a far, "
        "weakly textured sky, things standing on the ground)",
    )
    room_probability: float = _knob(
        0.0,
        "procedural scenes: fraction laid out as a room (a floor meeting a back wall, things standing on the floor)",
    )
    thin_probability: float = _knob(
        0.0,
        "procedural scenes: fraction of the foreground surfaces that are thin structures (wires, stems, pipes, "
        "chair legs: bars 1-6 px wide, often crossing) well in front of the background",
    )
    flat_probability: float = _knob(
        0.0,
        "procedural scenes: fraction of the surfaces that are large, weakly textured planes whose brightness "
        "changes slowly across them (walls, tables, floors)",
    )
    repetitive_probability: float = _knob(
        0.0,
        "procedural scenes: fraction of the surfaces painted with a pattern that repeats every 4-40 px along the "
        "rows (stripes, checkers, grids, dots: matches one period apart look alike)",
    )
    wide_range_probability: float = _knob(
        0.0,
        "procedural scenes: fraction whose largest disparity is drawn between max_disparity and wide_max_disparity "
        "instead of max_disparity (wider disparity ranges)",
    )
    reflective_probability: float = _knob(
        0.0,
        "procedural scenes: fraction of the foreground surfaces that reflect a farther scene over their own texture "
        "(car bodies and windows, glossy floors, glass: a second layer moving between the views by less than the "
        "surface)",
    )
    row_offset_probability: float = _knob(
        0.0,
        "procedural scenes: fraction of the pairs whose right view's rows are off the left's (an imperfect "
        "rectification: a shift and two tilts of vertical offsets, up to row_offset px)",
    )
    row_offset: float = _knob(2.0, "largest vertical offset (px) of the pairs whose rows are off")
    wide_max_disparity: float | None = _knob(
        None,
        "largest disparity (px) of the wide-range procedural scenes [256 * crop_width / 512, at least max_disparity]",
    )
    real_scale_range: tuple[float, float] = _knob(
        (0.8, 1.25), "random rescale range of real pairs before cropping (raised where a pair is smaller than the crop)"
    )
    color_jitter: float = _knob(0.1, "real pairs: each view's channels get independent gains in 1 +- this")
    batch_size: int = _knob(8, "pairs per step and per process")
    lr: float = _knob(4e-4, "peak learning rate")
    betas: tuple[float, float] = _knob((0.9, 0.999), "Adam betas")
    weight_decay: float = _knob(0.0, "decoupled weight decay (AdamW); 0 is plain Adam")
    schedule: Schedule = _knob(
        "one-cycle",
        "lr schedule after warm-up: cosine (one-cycle) or linear decay to 0, constant, or flat-decay "
        "(constant, then linear to 0 over the last decay_steps)",
    )
    warmup_fraction: float = _knob(0.01, "fraction of the schedule spent warming the lr up linearly from 0")
    decay_steps: int = _knob(400, "flat-decay: the lr decays linearly to 0 over this many last steps of the schedule")
    gamma: float = _knob(0.8, "sequence-loss decay: prediction i of n has weight gamma^(n-i)")
    train_iters: tuple[int, int, int] | None = _knob(
        None, "ARM iterations at 1/16, 1/8, 1/4 in training (fewer = faster steps) [the model's own]"
    )
    two_pass_fraction: float = _knob(
        0.0,
        "fraction of the steps that compute their pairs as two-pass inference does: the network's own disparity at "
        "half resolution (no gradient), then the full-resolution refinement from it, trained (the path that "
        "two_pass and warm starts take; crops must then be multiples of 64)",
    )
    loss_max_disparity: float = _knob(512.0, "ground truth at or above this (px) is ignored by the loss")
    matching_weight: float = _knob(
        0.0, "weight of the training-only feature matching loss (training.loss.matching_loss); 0: off"
    )
    grad_clip: float = _knob(1.0, "clip the gradient norm to this (0: no clipping)")
    ema_decay: float = _knob(
        0.0,
        "checkpoints serve an exponential moving average of the weights with this decay per step "
        "(e.g. 0.999, about the last 1/(1-decay) steps); the raw weights are kept for resuming. 0: off",
    )
    max_steps: int = _knob(150_000, "train until this optimiser step (counted across resumes)")
    schedule_steps: int | None = _knob(
        None, "length of the lr schedule in steps [max_steps]; longer lets a run stop early and resume"
    )
    max_minutes: float | None = _knob(None, "stop after this many minutes of this run, saving a checkpoint")
    precision: Precision = _knob("auto", "auto: bf16 autocast on CUDA, fp32 on CPU")
    fused_adamw: Switch = _knob("auto", "AdamW as one fused kernel per step (auto: on CUDA only)")
    compile: bool = _knob(
        False,
        "torch.compile the network for training: fewer, fused kernels per step after a compile of a "
        "minute or more (for long CUDA runs; the checkpoints are the same)",
    )
    compile_mode: CompileMode = _knob(
        "default",
        "torch.compile mode when compile is on: reduce-overhead replays the step's kernels as CUDA graphs "
        "(the crops have one shape)",
    )
    channels_last: bool = _knob(
        False, "train with the network's weights and the images in channels-last memory format (NHWC)"
    )
    device: str = _knob("auto", "auto (cuda if available, else cpu), cpu, cuda, cuda:N")
    seed: int = _knob(0, "seed of the initial weights and of every batch")
    out_dir: str = _knob("runs/train", "folder for checkpoints, the CSV log and the loss curve")
    log_every: int = _knob(10, "steps per CSV row (loss averaged over them)")
    checkpoint_every: int = _knob(1000, "steps between checkpoints (one is also saved at the end)")
    num_workers: int = _knob(2, "worker processes loading real pairs (0: in the training process)")
    val_data: str | None = _knob(None, "dataset evaluated at every checkpoint (mean EPE and bad-2 go to the log)")

    def __post_init__(self) -> None:
        for name in ("crop_height", "crop_width"):
            if getattr(self, name) % 32:
                raise ValueError(f"{name}={getattr(self, name)} must be a multiple of 32")
        if not self.sources:
            raise ValueError("at least one training source is needed")
        if self.batch_size < 1 or self.max_steps < 1 or self.log_every < 1 or self.checkpoint_every < 1:
            raise ValueError("batch_size, max_steps, log_every and checkpoint_every must be positive")
        if not 0.0 <= self.ema_decay < 1.0:
            raise ValueError(f"ema_decay must be in [0, 1), got {self.ema_decay}")
        if not 0.0 <= self.two_pass_fraction <= 1.0:
            raise ValueError(f"two_pass_fraction must be in [0, 1], got {self.two_pass_fraction}")
        if self.two_pass_fraction > 0 and (self.crop_height % 64 or self.crop_width % 64):
            raise ValueError(
                f"two-pass steps need crops that are multiples of 64 (their half is what the network sees), "
                f"got {self.crop_height}x{self.crop_width}"
            )
        if self.schedule_steps is not None and self.schedule_steps < 1:
            raise ValueError("schedule_steps must be positive")
        low, high = self.real_scale_range
        if not 0 < low <= high:
            raise ValueError(f"real_scale_range must be 0 < low <= high, got {self.real_scale_range}")
        self.scene_config  # noqa: B018 (raises ValueError where the scene settings are invalid)

    @property
    def scene_config(self) -> SceneConfig:
        """The procedural generator's settings for this run's crops."""
        return SceneConfig(
            height=self.crop_height,
            width=self.crop_width,
            max_disparity=self.max_disparity,
            photo_textures=self.photo_textures,
            texel_size=self.texel_size,
            supersample=self.supersample,
            road_probability=self.road_probability,
            room_probability=self.room_probability,
            curve_probability=self.curve_probability,
            photometric=PhotometricConfig(vignetting=self.vignetting, jpeg_probability=self.jpeg_probability),
            lighting_probability=self.lighting_probability,
            specular_probability=self.specular_probability,
            thin_probability=self.thin_probability,
            flat_probability=self.flat_probability,
            repetitive_probability=self.repetitive_probability,
            wide_range_probability=self.wide_range_probability,
            wide_max_disparity=self.wide_max_disparity,
            reflective_probability=self.reflective_probability,
            row_offset_probability=self.row_offset_probability,
            row_offset=self.row_offset,
        )

    @property
    def scene_max_disparity(self) -> float:
        """Largest disparity of the procedural scenes (px): max_disparity or its default."""
        resolved = self.scene_config.max_disparity
        assert resolved is not None  # SceneConfig resolves its default
        return resolved

    @property
    def schedule_length(self) -> int:
        """Steps over which the lr schedule runs (schedule_steps, else max_steps)."""
        return self.schedule_steps or self.max_steps

    def to_dict(self) -> dict[str, Any]:
        """Plain dict of builtins (sources as {"path", "weight"} dicts), for checkpoints and JSON."""
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> TrainConfig:
        """Inverse of `to_dict`; unknown keys are an error, missing keys take the defaults."""
        known = {f.name for f in fields(cls)}
        unknown = set(values) - known
        if unknown:
            raise ValueError(f"unknown TrainConfig fields: {sorted(unknown)}")
        converted = dict(values)
        if "sources" in converted:
            converted["sources"] = tuple(DataSource(**s) for s in converted["sources"])
        for name in ("texel_size", "real_scale_range", "betas", "train_iters"):
            if converted.get(name) is not None:
                converted[name] = tuple(converted[name])
        return cls(**converted)


PRESETS: dict[str, TrainConfig] = {
    # Paper, pre-training stage: Adam 4e-4, betas 0.9/0.999, 150k steps, crops 384x512, gamma 0.8.
    "pretrain": TrainConfig(),
    # Paper, fine-tuning stage: a further 50k steps at lr 1e-4 (start it with --init-weights).
    "finetune": TrainConfig(lr=1e-4, max_steps=50_000, schedule="linear"),
}


def preset(name: str, **overrides: Any) -> TrainConfig:
    """The named preset ("pretrain" | "finetune") with `overrides` applied."""
    if name not in PRESETS:
        raise ValueError(f"unknown training preset {name!r}; choose one of {sorted(PRESETS)}")
    return replace(PRESETS[name], **overrides)
