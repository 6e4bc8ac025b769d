"""Update block of the adaptive recurrent module: motion encoder, ConvGRU, disparity and mask heads."""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from .config import GruKernels, ModelConfig
from .convolution import conv1xk, input_response
from .correlation import CANDIDATES
from .upsample import UPSAMPLE_FACTOR

GATE_KERNEL_CHAINS: dict[str, tuple[int, ...]] = {
    "1x5": (5,),
    "1x15": (15,),
    "1x5+1x15": (15, 5),
    "1x5+1x15+1x31": (31, 15, 5),
}
"""Horizontal z/r gate of the separable GRU: widths of the 1xk convs applied in sequence."""


def zr_gates(in_channels: int, hidden: int, widths: tuple[int, ...], vertical: bool = False) -> nn.Sequential:
    """The z and r gates computed together: convs of the given widths in sequence, in -> 2*hidden
    first, then grouped 2*hidden -> 2*hidden so that z (first half) and r (second half) stay two
    independent gates. One wide conv instead of two narrow ones is what makes this fast on a CPU."""
    convs = [conv1xk(in_channels, 2 * hidden, widths[0], vertical)]
    convs += [conv1xk(2 * hidden, 2 * hidden, k, vertical, groups=2) for k in widths[1:]]
    return nn.Sequential(*convs)


ContextTerms = tuple[Tensor, ...]
"""The GRU's gate convolutions' responses to the context (each (B, gate channels, h, w), no bias):
constant over a stage's iterations, computed once per stage (``input_response``)."""


def gru_step(
    h: Tensor, motion: Tensor, context_zr: Tensor, context_q: Tensor, zr: nn.Sequential, q: nn.Conv2d
) -> Tensor:
    """One ConvGRU update: h (B,Ch,h,w) -> new h (B,Ch,h,w), with input x = [motion, context].

    The gates read [h, x] and [r * h, x]; the context's share of their first convolutions is
    given precomputed (``context_zr``, ``context_q``), so only [h, motion] is convolved here.
    ``zr``: the z/r gate's convs in sequence, the first reading the input."""
    first, rest = zr[0], zr[1:]
    assert isinstance(first, nn.Conv2d)
    gates = rest(input_response(first, torch.cat((h, motion), dim=1), 0, True) + context_zr)
    z, r = torch.sigmoid(gates).chunk(2, dim=1)
    candidate = torch.tanh(input_response(q, torch.cat((r * h, motion), dim=1), 0, True) + context_q)
    return (1 - z) * h + z * candidate


def context_response(conv: nn.Module, context: Tensor) -> Tensor:
    """A gate's (first) convolution's response to the context, the last third of the gate input
    [h, motion, context]."""
    first = conv[0] if isinstance(conv, nn.Sequential) else conv
    assert isinstance(first, nn.Conv2d)
    return input_response(first, context, first.in_channels - context.shape[1], False)


class ConvGRU(nn.Module):
    """Plain ConvGRU with 3x3 kernels (the ``3x3`` ablation)."""

    def __init__(self, hidden: int, input_dim: int) -> None:
        super().__init__()
        c = hidden + input_dim
        self.zr = nn.Sequential(nn.Conv2d(c, 2 * hidden, 3, padding=1))
        self.q = nn.Conv2d(c, hidden, 3, padding=1)

    def context_terms(self, context: Tensor) -> ContextTerms:
        return context_response(self.zr, context), context_response(self.q, context)

    def forward(self, h: Tensor, motion: Tensor, terms: ContextTerms) -> Tensor:
        return gru_step(h, motion, terms[0], terms[1], self.zr, self.q)


class SeparableConvGRU(nn.Module):
    """Separable ConvGRU: a horizontal pass, then a vertical one (5x1 gates).

    Horizontal z and r gates: the chain of ``GATE_KERNEL_CHAINS[kernels]`` (for Lite's super
    kernel ``1x5+1x15``: a 1x15 conv followed by a 1x5 conv); the candidate q stays 1x5.
    """

    def __init__(self, hidden: int, input_dim: int, kernels: GruKernels) -> None:
        super().__init__()
        c = hidden + input_dim
        self.zr1 = zr_gates(c, hidden, GATE_KERNEL_CHAINS[kernels])
        self.q1 = conv1xk(c, hidden, 5)
        self.zr2 = zr_gates(c, hidden, (5,), vertical=True)
        self.q2 = conv1xk(c, hidden, 5, vertical=True)

    def context_terms(self, context: Tensor) -> ContextTerms:
        return tuple(context_response(conv, context) for conv in (self.zr1, self.q1, self.zr2, self.q2))

    def forward(self, h: Tensor, motion: Tensor, terms: ContextTerms) -> Tensor:
        h = gru_step(h, motion, terms[0], terms[1], self.zr1, self.q1)
        return gru_step(h, motion, terms[2], terms[3], self.zr2, self.q2)


class MotionEncoder(nn.Module):
    """(V_n, d) -> motion features (B, hidden, h, w): the last channel is d itself.

    Correlation branch 1x1 then 3x3, disparity branch 7x7 then 3x3, fused by a 3x3 conv.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        (c1, c2), (d1, d2) = config.corr_hidden, config.disp_hidden
        self.corr1 = nn.Conv2d(config.corr_groups * CANDIDATES, c1, 1)
        self.corr2 = nn.Conv2d(c1, c2, 3, padding=1)
        self.disp1 = nn.Conv2d(1, d1, 7, padding=3)
        self.disp2 = nn.Conv2d(d1, d2, 3, padding=1)
        self.fuse = nn.Conv2d(c2 + d2, config.hidden_dim - 1, 3, padding=1)

    def forward(self, volume: Tensor, disparity: Tensor) -> Tensor:
        corr = F.relu(self.corr2(F.relu(self.corr1(volume))))
        disp = F.relu(self.disp2(F.relu(self.disp1(disparity))))
        return torch.cat((F.relu(self.fuse(torch.cat((corr, disp), dim=1))), disparity), dim=1)


def head(in_channels: int, hidden: int, out_channels: int, out_kernel: int) -> nn.Sequential:
    """3x3 conv + ReLU, then an ``out_kernel`` conv to ``out_channels``."""
    return nn.Sequential(
        nn.Conv2d(in_channels, hidden, 3, padding=1),
        nn.ReLU(inplace=True),
        nn.Conv2d(hidden, out_channels, out_kernel, padding=out_kernel // 2),
    )


class UpdateBlock(nn.Module):
    """GRU update of the hidden state, then the disparity update and the upsampling mask."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        hidden = config.hidden_dim
        self.encoder = MotionEncoder(config)
        input_dim = 2 * hidden  # motion features + context
        self.gru: ConvGRU | SeparableConvGRU = (
            ConvGRU(hidden, input_dim)
            if config.gru_kernels == "3x3"
            else SeparableConvGRU(hidden, input_dim, config.gru_kernels)
        )
        self.disparity_head = head(hidden, config.head_hidden, 1, 3)
        self.mask_head = head(hidden, config.head_hidden, 9 * UPSAMPLE_FACTOR**2, 1)

    def context_terms(self, context: Tensor) -> ContextTerms:
        """The GRU's per-stage constants from the context (B, Ch, h, w) of this scale."""
        return self.gru.context_terms(context)

    def forward(
        self, hidden: Tensor, context: ContextTerms, volume: Tensor, disparity: Tensor
    ) -> tuple[Tensor, Tensor]:
        """
        Args:
            hidden: (B, Ch, h, w) GRU state. context: ``context_terms`` of this scale's context.
            volume: (B, 36, h, w) cost volume V_n. disparity: (B, 1, h, w) d_{n-1}, pixels.
        Returns:
            new hidden state (B, Ch, h, w) and the disparity update Δd (B, 1, h, w), pixels.
        """
        hidden = self.gru(hidden, self.encoder(volume, disparity), context)
        return hidden, self.disparity_head(hidden)

    def upsample_mask(self, hidden: Tensor) -> Tensor:
        """Convex-upsampling logits (B, 9*16, h, w), scaled by 0.25 as in RAFT."""
        logits: Tensor = self.mask_head(hidden)
        return 0.25 * logits
