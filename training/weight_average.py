"""An exponential moving average of the network's weights: what checkpoints serve when
`TrainConfig.ema_decay` > 0 (the raw weights are kept beside it for resuming)."""

from __future__ import annotations

import copy

import torch

from crestereo_pp.model import CREStereoPP


class WeightAverage:
    """After every optimiser step: average <- decay * average + (1 - decay) * weights.

    `network` is a separate copy of the trained network whose parameters hold the average (it
    starts as a copy of the weights it is given); its buffers follow the trained network's. It is
    never trained, and the update reads nothing back to the host, so it adds no device sync.
    """

    def __init__(self, network: CREStereoPP, decay: float) -> None:
        if not 0.0 < decay < 1.0:
            raise ValueError(f"an average's decay must be in (0, 1), got {decay}")
        self.decay = decay
        self.network = copy.deepcopy(network).requires_grad_(False)

    @torch.no_grad()
    def update(self, trained: CREStereoPP) -> None:
        """Move the average towards `trained`'s current weights by (1 - decay)."""
        averaged: list[torch.Tensor] = list(self.network.parameters())
        torch._foreach_lerp_(averaged, [p.detach() for p in trained.parameters()], 1.0 - self.decay)
        for mine, theirs in zip(self.network.buffers(), trained.buffers(), strict=True):
            mine.copy_(theirs)
