"""Group-wise local correlation (paper eq. 1): the cost volume V_n fed to the GRU."""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor
from torch.nn import functional as F

Window = Literal["1x9", "3x3"]
"""Search window around each pixel: a horizontal line of 9 or a 3x3 square. ARM alternates them."""

CANDIDATES = 9
"""Candidates per window (1x9 or 3x3)."""


def window_for_iteration(iteration: int) -> Window:
    """The window alternates from one iteration to the next, starting with the 1x9 line."""
    return "1x9" if iteration % 2 == 0 else "3x3"


def group_correlation(left: Tensor, warped_right: Tensor, groups: int, window: Window) -> Tensor:
    """Local group-wise correlation between left and warped right features.

        V[g * 9 + r](p) = mean over channels c of group g of  F_L(p)[c] * F^_R(p + r)[c]

    for the 9 displacements r of ``window`` (row-major; zeros read outside the map).

    Args:
        left, warped_right: (B, C, h, w) features, C divisible by ``groups``.
    Returns:
        (B, groups * 9, h, w) cost volume, group-major.
    """
    b, c, h, w = left.shape
    if window == "1x9":
        padded = F.pad(warped_right, (4, 4, 0, 0))
        shifts = [(0, dx) for dx in range(CANDIDATES)]
    else:
        padded = F.pad(warped_right, (1, 1, 1, 1))
        shifts = [(dy, dx) for dy in range(3) for dx in range(3)]
    candidates = [padded[:, :, dy : dy + h, dx : dx + w] for dy, dx in shifts]  # views, no copies
    per_group = c // groups
    if torch.compiler.is_exporting():
        # Exported graphs (OpenVINO, ONNX) take one product and one mean over the stacked
        # candidates: lite's OpenVINO graph ran 8 % faster in bf16 so than with a mean per
        # candidate (6 % less time per dev pair). Eager torch takes one candidate at a time: the
        # stack is a copy, which made it 12 % slower (and autograd would keep it).
        stacked = torch.stack(candidates, dim=2).view(b, groups, per_group, CANDIDATES, h, w)
        return (left.view(b, groups, per_group, 1, h, w) * stacked).mean(2).view(b, groups * CANDIDATES, h, w)
    left_groups = left.view(b, groups, per_group, h, w)
    volume = [(left_groups * candidate.view(b, groups, per_group, h, w)).mean(2) for candidate in candidates]
    return torch.stack(volume, dim=2).view(b, groups * CANDIDATES, h, w)
