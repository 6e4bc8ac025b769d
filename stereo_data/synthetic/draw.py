"""The procedural scenes' one source of randomness."""

from __future__ import annotations

import math

import torch


class Draw:
    """Random tensors on one device from one generator (the only source of randomness): each
    method returns a tensor of the given `shape` on `device`, and draws from the generator in
    the order called, so that the same calls give the same tensors bit for bit."""

    def __init__(self, generator: torch.Generator, device: torch.device) -> None:
        self.generator = generator
        self.device = device

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
