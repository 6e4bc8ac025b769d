"""Update block of the adaptive recurrent module: motion encoder, ConvGRU, disparity and mask heads."""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from .config import GruKernels, ModelConfig
from .correlation import CANDIDATES
from .upsample import UPSAMPLE_FACTOR

GATE_KERNEL_CHAINS: dict[str, tuple[int, ...]] = {
    "1x5": (5,),
    "1x15": (15,),
    "1x5+1x15": (15, 5),
    "1x5+1x15+1x31": (31, 15, 5),
}
"""Horizontal z/r gate of the separable GRU: widths of the 1xk convs applied in sequence."""


WIDE_KERNEL = 9
"""Horizontal kernels at least this wide run as the transposed (kx1) convolution: oneDNN computes a
1x15 conv 1.8x faster forward and 2x faster forward + backward that way (bench/train_speed.py)."""


class WideHorizontalConv(nn.Conv2d):
    """A 'same'-padded 1xk convolution (weight (out, in/groups, 1, k), as nn.Conv2d) computed on
    the transposed map as a kx1 convolution; the result is the same up to float rounding."""

    def forward(self, x: Tensor) -> Tensor:
        padding = self.padding
        assert not isinstance(padding, str)  # always built with a (0, k // 2) tuple
        out = F.conv2d(
            x.transpose(2, 3),
            self.weight.transpose(2, 3),
            self.bias,
            padding=(padding[1], padding[0]),
            groups=self.groups,
        )
        return out.transpose(2, 3)


def conv1xk(in_channels: int, out_channels: int, k: int, vertical: bool = False, groups: int = 1) -> nn.Conv2d:
    """A 'same'-padded 1xk (or kx1 when ``vertical``) convolution."""
    if not vertical and k >= WIDE_KERNEL:
        return WideHorizontalConv(in_channels, out_channels, (1, k), padding=(0, k // 2), groups=groups)
    size, pad = ((k, 1), (k // 2, 0)) if vertical else ((1, k), (0, k // 2))
    return nn.Conv2d(in_channels, out_channels, size, padding=pad, groups=groups)


def zr_gates(in_channels: int, hidden: int, widths: tuple[int, ...], vertical: bool = False) -> nn.Sequential:
    """The z and r gates computed together: convs of the given widths in sequence, in -> 2*hidden
    first, then grouped 2*hidden -> 2*hidden so that z (first half) and r (second half) stay two
    independent gates. One wide conv instead of two narrow ones is what makes this fast on a CPU."""
    convs = [conv1xk(in_channels, 2 * hidden, widths[0], vertical)]
    convs += [conv1xk(2 * hidden, 2 * hidden, k, vertical, groups=2) for k in widths[1:]]
    return nn.Sequential(*convs)


def gru_step(h: Tensor, x: Tensor, conv_zr: nn.Module, conv_q: nn.Module) -> Tensor:
    """One ConvGRU update: h (B,Ch,h,w) with input x (B,Cx,h,w) -> new h (B,Ch,h,w)."""
    z, r = torch.sigmoid(conv_zr(torch.cat((h, x), dim=1))).chunk(2, dim=1)
    q = torch.tanh(conv_q(torch.cat((r * h, x), dim=1)))
    return (1 - z) * h + z * q


class ConvGRU(nn.Module):
    """Plain ConvGRU with 3x3 kernels (the ``3x3`` ablation)."""

    def __init__(self, hidden: int, input_dim: int) -> None:
        super().__init__()
        c = hidden + input_dim
        self.zr = nn.Conv2d(c, 2 * hidden, 3, padding=1)
        self.q = nn.Conv2d(c, hidden, 3, padding=1)

    def forward(self, h: Tensor, x: Tensor) -> Tensor:
        return gru_step(h, x, self.zr, self.q)


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

    def forward(self, h: Tensor, x: Tensor) -> Tensor:
        h = gru_step(h, x, self.zr1, self.q1)
        return gru_step(h, x, self.zr2, self.q2)


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
        self.gru: nn.Module = (
            ConvGRU(hidden, input_dim)
            if config.gru_kernels == "3x3"
            else SeparableConvGRU(hidden, input_dim, config.gru_kernels)
        )
        self.disparity_head = head(hidden, config.head_hidden, 1, 3)
        self.mask_head = head(hidden, config.head_hidden, 9 * UPSAMPLE_FACTOR**2, 1)

    def forward(self, hidden: Tensor, context: Tensor, volume: Tensor, disparity: Tensor) -> tuple[Tensor, Tensor]:
        """
        Args:
            hidden, context: (B, Ch, h, w) GRU state and context of this scale.
            volume: (B, 36, h, w) cost volume V_n. disparity: (B, 1, h, w) d_{n-1}, pixels.
        Returns:
            new hidden state (B, Ch, h, w) and the disparity update Δd (B, 1, h, w), pixels.
        """
        x = torch.cat((self.encoder(volume, disparity), context), dim=1)
        hidden = self.gru(hidden, x)
        return hidden, self.disparity_head(hidden)

    def upsample_mask(self, hidden: Tensor) -> Tensor:
        """Convex-upsampling logits (B, 9*16, h, w), scaled by 0.25 as in RAFT."""
        logits: Tensor = self.mask_head(hidden)
        return 0.25 * logits
