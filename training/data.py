"""Training batches: a weighted mixture of procedural scenes and real dataset pairs.

Every batch is a pure function of (seed, step, rank): which source each pair comes from, which
real pair, its crop and its photometric change are drawn from a generator seeded with those three
numbers, and the procedural scenes from a seed drawn there too. So a resumed run sees exactly
the batches the uninterrupted run would have seen, whatever the number of loader workers, and
every rank of a distributed run sees different pairs.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from crestereo_pp.stereo_data.readers import StereoSample, open_dataset
from crestereo_pp.stereo_data.synthetic import SceneGenerator

from .config import SYNTHETIC, TrainConfig


@dataclass(frozen=True)
class TrainingBatch:
    """One step's pairs, all on one device.

    left, right: float32 (B, 3, H, W) RGB in [0, 255]; disparity: float32 (B, 1, H, W), positive
    pixels of the left view (0 where unknown); valid: bool (B, 1, H, W), True where known.
    """

    left: torch.Tensor
    right: torch.Tensor
    disparity: torch.Tensor
    valid: torch.Tensor

    def to(self, device: torch.device) -> TrainingBatch:
        return TrainingBatch(*(t.to(device) for t in (self.left, self.right, self.disparity, self.valid)))

    def channels_last(self) -> TrainingBatch:
        """The same pairs stored channels-last (NHWC in memory; the shapes stay (B, C, H, W))."""
        tensors = (self.left, self.right, self.disparity, self.valid)
        return TrainingBatch(*(t.contiguous(memory_format=torch.channels_last) for t in tensors))

    @staticmethod
    def concatenate(parts: Sequence[TrainingBatch]) -> TrainingBatch:
        return TrainingBatch(
            left=torch.cat([p.left for p in parts]),
            right=torch.cat([p.right for p in parts]),
            disparity=torch.cat([p.disparity for p in parts]),
            valid=torch.cat([p.valid for p in parts]),
        )


@dataclass(frozen=True)
class RealDraw:
    """One real pair of a step: dataset `source` (index among the real sources), pair `index`
    in it, and `seed` of its scale, crop and photometric change."""

    source: int
    index: int
    seed: int


@dataclass(frozen=True)
class StepPlan:
    """What a step's batch is made of: `synthetic_count` procedural scenes generated with
    `synthetic_seed`, then the `real` pairs."""

    synthetic_count: int
    synthetic_seed: int
    real: tuple[RealDraw, ...]


def plan_step(config: TrainConfig, real_sizes: Sequence[int], step: int, rank: int) -> StepPlan:
    """Draw the composition of batch `step` on `rank`.

    real_sizes: number of pairs of each real source, in the order of `config.sources` without
    the synthetic one. Each pair of the batch picks its source with probability proportional to
    the sources' weights; real pairs are drawn uniformly with replacement.
    """
    rng = np.random.default_rng([config.seed, step, rank])
    weights = np.array([s.weight for s in config.sources], dtype=np.float64)
    counts = rng.multinomial(config.batch_size, weights / weights.sum())
    synthetic_count = 0
    real: list[RealDraw] = []
    real_source = 0
    for source, count in zip(config.sources, counts, strict=True):
        if source.path == SYNTHETIC:
            synthetic_count += int(count)
            continue
        for _ in range(count):
            index = int(rng.integers(real_sizes[real_source]))
            real.append(RealDraw(real_source, index, int(rng.integers(2**31))))
        real_source += 1
    return StepPlan(synthetic_count, int(rng.integers(2**31)), tuple(real))


def augment_real_pair(
    sample: StereoSample,
    crop_height: int,
    crop_width: int,
    scale_range: tuple[float, float],
    color_jitter: float,
    seed: int,
) -> TrainingBatch:
    """Randomly rescale, crop and recolour one real pair into a batch of one (CPU tensors).

    The scale is drawn uniformly in `scale_range`, raised where needed so the rescaled pair covers
    the crop; disparities are multiplied by the horizontal scale and resampled nearest-neighbour
    (sparse ground truth stays sparse, never blended with unknown pixels). Each view's RGB
    channels are multiplied by independent gains in [1 - color_jitter, 1 + color_jitter]. No
    flips: a mirrored pair is not a valid stereo pair without swapping the views.
    """
    rng = np.random.default_rng(seed)
    height, width = sample.disparity.shape
    scale = max(rng.uniform(*scale_range), crop_height / height, crop_width / width)
    new_width, new_height = max(crop_width, round(width * scale)), max(crop_height, round(height * scale))
    valid = sample.valid & np.isfinite(sample.disparity) & (sample.disparity > 0)
    disparity = np.where(valid, sample.disparity, 0.0).astype(np.float32)
    size = (new_width, new_height)
    left = cv2.resize(sample.left, size, interpolation=cv2.INTER_LINEAR)
    right = cv2.resize(sample.right, size, interpolation=cv2.INTER_LINEAR)
    disparity = cv2.resize(disparity, size, interpolation=cv2.INTER_NEAREST) * (new_width / width)
    valid = cv2.resize(valid.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST).astype(bool)

    top = int(rng.integers(new_height - crop_height + 1))
    left_edge = int(rng.integers(new_width - crop_width + 1))
    window = (slice(top, top + crop_height), slice(left_edge, left_edge + crop_width))

    def recolor(image: np.ndarray) -> torch.Tensor:
        gains = rng.uniform(1.0 - color_jitter, 1.0 + color_jitter, size=3).astype(np.float32)
        pixels = np.clip(image[window].astype(np.float32) * gains, 0.0, 255.0)
        return torch.from_numpy(pixels).permute(2, 0, 1)[None]

    return TrainingBatch(
        left=recolor(left),
        right=recolor(right),
        disparity=torch.from_numpy(np.ascontiguousarray(disparity[window]))[None, None],
        valid=torch.from_numpy(np.ascontiguousarray(valid[window]))[None, None],
    )


class HostPartsByStep(Dataset["TrainingBatch | None"]):
    """Map-style dataset whose item `step` is the part of that step's batch made on the host (a
    CPU TrainingBatch, or None when there is none): the procedural scenes when `generator` is
    given (a CPU generator), then the real pairs. A DataLoader with workers thus prepares the next
    steps in other processes while the current one trains."""

    def __init__(
        self,
        config: TrainConfig,
        datasets: Sequence[Sequence[StereoSample]],
        rank: int,
        generator: SceneGenerator | None = None,
    ) -> None:
        self.config = config
        self.datasets = datasets
        self.rank = rank
        self.generator = generator

    def __len__(self) -> int:
        return self.config.max_steps

    def __getitem__(self, step: int) -> TrainingBatch | None:
        plan = plan_step(self.config, [len(d) for d in self.datasets], step, self.rank)
        c = self.config
        parts = [synthetic_part(self.generator, plan)] if self.generator is not None and plan.synthetic_count else []
        parts += [
            augment_real_pair(
                self.datasets[draw.source][draw.index],
                c.crop_height,
                c.crop_width,
                c.real_scale_range,
                c.color_jitter,
                draw.seed,
            )
            for draw in plan.real
        ]
        return TrainingBatch.concatenate(parts) if parts else None


def synthetic_part(generator: SceneGenerator, plan: StepPlan) -> TrainingBatch:
    """The procedural scenes of a step, on the generator's device (0 disparity where unknown)."""
    scenes = generator.generate(batch_size=plan.synthetic_count, seed=plan.synthetic_seed)
    disparity = torch.where(scenes.valid, scenes.disparity, torch.zeros_like(scenes.disparity))
    return TrainingBatch(scenes.left, scenes.right, disparity, scenes.valid)


class TrainingData:
    """Iterates over the batches of steps [start_step, max_steps) of one rank, on `device`.

    On a CPU device the procedural scenes are generated in the loader's worker processes with
    everything else (config.num_workers; 0 = in this process), off the training step's critical
    path; on a GPU they are generated on the GPU, in this process."""

    def __init__(self, config: TrainConfig, rank: int, device: torch.device) -> None:
        self.config = config
        self.rank = rank
        self.device = device
        self.real_datasets = [open_dataset(s.path) for s in config.sources if s.path != SYNTHETIC]
        uses_scenes = any(s.path == SYNTHETIC for s in config.sources)
        self.generator = SceneGenerator(config.scene_config, device=device) if uses_scenes else None
        self.scenes_on_host = self.generator is not None and device.type == "cpu"

    def batches(self, start_step: int) -> Iterator[TrainingBatch]:
        host_parts = HostPartsByStep(
            self.config, self.real_datasets, self.rank, self.generator if self.scenes_on_host else None
        )
        loader = DataLoader(
            host_parts,
            batch_size=None,
            sampler=range(start_step, self.config.max_steps),
            num_workers=self.config.num_workers if self.real_datasets or self.scenes_on_host else 0,
        )
        sizes = [len(d) for d in self.real_datasets]
        for step, host_part in zip(range(start_step, self.config.max_steps), loader, strict=True):
            plan = plan_step(self.config, sizes, step, self.rank)
            parts = []
            if plan.synthetic_count and not self.scenes_on_host:
                assert self.generator is not None  # plan_step draws scenes only from a synthetic source
                parts.append(synthetic_part(self.generator, plan))
            if host_part is not None:
                parts.append(host_part.to(self.device))
            yield TrainingBatch.concatenate(parts)
