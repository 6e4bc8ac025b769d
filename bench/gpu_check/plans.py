"""What the GPU check's stages do: the real check on a GPU (`GPU`) or the CPU smoke run (`CPU_SMOKE`),
and how a stage ended (`StageResult`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from train_speed import GPU_RECIPE  # bench/'s sibling script (standard library only at import)

if TYPE_CHECKING:
    from crestereo_pp.model.config import ModelName

BENCH = Path(__file__).resolve().parents[1]
REPO = BENCH.parent

STAGES = ("environment", "tests", "bench", "service", "probe", "train", "arms")
DEFAULT_STAGES = STAGES[:-1]
"""What runs without --stages: every stage but arms, which measures a data candidate (--arm) and,
like train, takes the time left."""
MAX_FILES = 8
MAX_FILE_BYTES = 16 * 2**20
MAX_TRAVEL_BYTES = 64 * 2**20
"""What the device tool carries to the GPU machine at most: the checkout's tracked files and the
untracked ones git does not ignore, with the carried dev pairs (shared/data/stereo-dev). Over it,
the run is refused before it starts."""


@dataclass(frozen=True)
class Plan:
    """What the stages do: the real check on a GPU, or the CPU smoke run with tiny sizes.

    iters: inference iterations of the benchmark (None: each model's own); warmup_calls: untimed
    predict_batch calls before each timed row (3 with graphs: eager, capture, replay);
    stage_seconds: the most each stage may take (train: what is left of `minutes`);
    reserve_seconds: kept for the stages after it, so that an overrun cannot starve them.
    train: TrainConfig overrides of the shipped lite checkpoint's config for the training stage,
    which runs `train_steps` more steps at most; probe_steps: the untimed-then-timed steps of the
    probe run that measures the step rate; decay_fraction: the share of the run's steps over which
    flat-decay brings the lr to 0; train_tail_seconds: kept after the training time for the last
    validation, the checkpoint and the process's start; throughput_steps: timed steps per row of the
    throughput probe (of throughput_models, at throughput_factors times the recipe's batch, after
    throughput_warmup untimed steps), which stops a row after throughput_row_seconds and starts
    none with less left. The arms stage keeps arm_score_seconds per arm for scoring it, on the dev
    pairs and on arm_scenes procedural scenes of arm_scene_size drawn as the candidate trains.
    """

    device: str
    minutes: float
    tests: tuple[str, ...]
    models: tuple[ModelName, ...]
    sizes: tuple[tuple[int, int], ...]
    batches: tuple[int, ...]
    iters: tuple[int, int, int] | None
    warmup_calls: int
    timed_runs: int
    accuracy_pairs: int
    service_models: tuple[str, ...]
    service_requests: int
    stage_seconds: dict[str, float]
    reserve_seconds: dict[str, float]
    train: dict[str, Any]
    train_steps: int
    probe_steps: int
    decay_fraction: float
    train_tail_seconds: float
    throughput_models: tuple[ModelName, ...]
    throughput_factors: tuple[int, ...]
    throughput_warmup: int
    throughput_steps: int
    throughput_row_seconds: float
    arm_score_seconds: float
    arm_scenes: int
    arm_scene_size: tuple[int, int]
    label: str = ""


GPU = Plan(
    device="cuda",
    minutes=9.0,
    tests=("tests/gpu", "tests/stereo_data/test_synthetic_scenes.py::test_generator_runs_and_is_deterministic_on_cuda"),
    models=("lite", "full"),
    sizes=((384, 1248),),
    batches=(1, 8),
    iters=None,
    warmup_calls=3,
    timed_runs=20,
    accuracy_pairs=4,
    service_models=("lite", "full"),
    service_requests=16,
    stage_seconds={"environment": 60, "tests": 150, "bench": 90, "service": 120, "probe": 120},
    reserve_seconds={"environment": 420, "tests": 330, "bench": 150, "service": 90, "probe": 120},
    train=dict(GPU_RECIPE, log_every=25),  # the weights' recipe (scenes, max disparity, iterations) on the GPU step
    train_steps=1_000_000,
    probe_steps=40,
    decay_fraction=0.4,
    train_tail_seconds=75,
    throughput_models=("lite", "full"),
    throughput_factors=(1, 2, 4, 8),
    throughput_warmup=2,
    throughput_steps=8,
    throughput_row_seconds=8.0,
    arm_score_seconds=45.0,
    arm_scenes=16,
    arm_scene_size=(256, 512),
    label="GPU",
)
CPU_SMOKE = Plan(
    device="cpu",
    minutes=5.0,  # what the stages need on a quiet machine is about one minute; a busy one needs room
    tests=("tests/gpu/test_cuda_graphs.py", "tests/gpu/test_cuda_paths.py"),
    models=("lite", "full"),
    sizes=((32, 64),),
    batches=(1, 2),
    iters=(1, 1, 1),
    warmup_calls=1,
    timed_runs=2,
    accuracy_pairs=1,
    service_models=("lite",),
    service_requests=3,
    stage_seconds={"environment": 30, "tests": 90, "bench": 90, "service": 60, "probe": 60},
    reserve_seconds={"environment": 60, "tests": 50, "bench": 40, "service": 30, "probe": 20},
    train=dict(
        crop_height=64,
        crop_width=96,
        max_disparity=32.0,
        batch_size=1,
        train_iters=(1, 1, 1),
        lr=1e-4,
        schedule="flat-decay",
        warmup_fraction=0.0,
        log_every=1,
        num_workers=0,
    ),
    train_steps=2,
    probe_steps=2,
    decay_fraction=0.4,
    train_tail_seconds=20,
    throughput_models=("lite",),
    throughput_factors=(1, 2),
    throughput_warmup=1,
    throughput_steps=1,
    throughput_row_seconds=2.0,
    arm_score_seconds=40.0,
    arm_scenes=1,
    arm_scene_size=(64, 128),
    label="CPU smoke run (no GPU: no number here is a GPU number)",
)


@dataclass
class StageResult:
    """How a stage ended: status "passed" | "failed" | "skipped" | "timed out", its wall
    seconds, one line of detail, and its numbers (`data`, JSON-ready)."""

    status: str
    detail: str = ""
    seconds: float = 0.0
    data: dict[str, Any] = field(default_factory=dict)
