"""Convolution helpers shared by the network's blocks: wide horizontal convolutions, and a
convolution's response to one part of its input."""

from __future__ import annotations

from torch import Tensor, nn
from torch.nn import functional as F

WIDE_KERNEL = 9
"""Horizontal kernels at least this wide run as the transposed (kx1) convolution: oneDNN computes a
1x15 conv 1.8x faster forward and 2x faster forward + backward that way (bench/train_speed.py)."""


class WideHorizontalConv(nn.Conv2d):
    """A 'same'-padded 1xk convolution (weight (out, in/groups, 1, k), as nn.Conv2d) computed on
    the transposed map as a kx1 convolution; the result is the same up to float rounding."""

    def _conv_forward(self, input: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
        # nn.Conv2d.forward (and ``input_response``) compute through this method
        padding = self.padding
        assert not isinstance(padding, str)  # always built with a (0, k // 2) tuple
        out = F.conv2d(
            input.transpose(2, 3),
            weight.transpose(2, 3),
            bias,
            padding=(padding[1], padding[0]),
            groups=self.groups,
        )
        return out.transpose(2, 3)


def input_response(conv: nn.Conv2d, part: Tensor, first_channel: int, bias: bool) -> Tensor:
    """``conv``'s response to one part of its input: channels ``first_channel`` onwards, as many
    as ``part`` (B, Cp, h, w) has, with the bias added when ``bias``.

    A convolution of a concatenation is the sum of its responses to the parts (the bias counted
    once), so a part that stays the same over a stage's iterations (the context, the left
    features) is convolved once per stage instead of once per iteration. Ungrouped convs only."""
    assert conv.groups == 1
    weight = conv.weight[:, first_channel : first_channel + part.shape[1]]
    response: Tensor = conv._conv_forward(part, weight, conv.bias if bias else None)
    return response


def conv1xk(in_channels: int, out_channels: int, k: int, vertical: bool = False, groups: int = 1) -> nn.Conv2d:
    """A 'same'-padded 1xk (or kx1 when ``vertical``) convolution."""
    if not vertical and k >= WIDE_KERNEL:
        return WideHorizontalConv(in_channels, out_channels, (1, k), padding=(0, k // 2), groups=groups)
    size, pad = ((k, 1), (k // 2, 0)) if vertical else ((1, k), (0, k // 2))
    return nn.Conv2d(in_channels, out_channels, size, padding=pad, groups=groups)
