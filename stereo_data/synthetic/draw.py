"""The procedural scenes' one source of randomness."""

from __future__ import annotations

import math

import torch

SEEDS = 2**32
"""Seeds are in [0, SEEDS): torch's CPU generator keeps only a seed's low 32 bits (2**41 draws what
0 draws), so a larger seed would silently repeat a smaller one's scenes. Training draws its scene
seeds in [0, 2**31); the calibration's and the evaluation's lie above, in [2**31, 2**32)."""


class Draw:
    """Random tensors on one device from one generator (the only source of randomness): each
    method returns a tensor of the given `shape` on `device`, and draws from the generator in
    the order called, so that the same calls give the same tensors bit for bit."""

    def __init__(self, generator: torch.Generator, device: torch.device) -> None:
        self.generator = generator
        self.device = device

    @staticmethod
    def seeded(seed: int, device: torch.device) -> Draw:
        """A new generator on `device` seeded with `seed`, in [0, SEEDS) (ValueError otherwise)."""
        if not 0 <= seed < SEEDS:
            raise ValueError(f"scene seeds are in [0, 2**32) (a generator keeps 32 bits of a seed), got {seed}")
        return Draw(torch.Generator(device=device).manual_seed(seed), device)

    def uniform(self, shape: tuple[int, ...], low: float, high: float | torch.Tensor) -> torch.Tensor:
        """Uniform float32 in [low, high) (`high` a number or a tensor broadcasting with `shape`)."""
        sample = torch.rand(shape, generator=self.generator, device=self.device)
        return low + (high - low) * sample

    def log_uniform(self, shape: tuple[int, ...], low: float, high: float) -> torch.Tensor:
        """float32 whose logarithm is uniform in [log low, log high): as likely per octave."""
        return torch.exp(self.uniform(shape, math.log(low), math.log(high)))

    def normal(self, shape: tuple[int, ...]) -> torch.Tensor:
        """Standard normal float32."""
        return torch.randn(shape, generator=self.generator, device=self.device)

    def chance(self, shape: tuple[int, ...], probability: float) -> torch.Tensor:
        """bool, true with `probability`."""
        return self.uniform(shape, 0.0, 1.0) < probability

    def integers(self, shape: tuple[int, ...], low: int, high: int) -> torch.Tensor:
        """Uniform int64 in [low, high]."""
        return torch.randint(low, high + 1, shape, generator=self.generator, device=self.device)
