"""The pair computed twice, as given and upside down (``InferenceOptions.flip``), and the two
answers merged into one.

Turning both images upside down keeps a rectified pair rectified (rows stay rows, the match stays
on the same row, the same way), so the network's answer for it, turned back, is a second estimate
of the same map. The network's learned filters are not symmetric under the turn, so the two
answers fail in different places. Where they agree within ``AGREEMENT_PX`` their mean is kept (it
averages out noise); where they disagree, one of them is wrong, and the one whose uncertainty is
lower is kept. The uncertainty served is the mean of the two (on the dev pairs it ranks the merged
answer's errors a little better than the given pair's uncertainty, and stays calibrated: the
model card, "Flip ensemble").
"""

from __future__ import annotations

import torch
from torch import Tensor

AGREEMENT_PX = 2.0
"""Answers within this many pixels of each other are averaged; farther apart, the less uncertain
one is kept. Chosen on procedural validation scenes (40 plain, 24 with rooms, flat surfaces and
thin structures: 2 px was best of 0.5, 1, 2 and 4), never on real pairs."""


def merge_flipped(
    disparity: Tensor, uncertainty: Tensor, turned_disparity: Tensor, turned_uncertainty: Tensor
) -> tuple[Tensor, Tensor]:
    """One answer from two answers of the same pairs: `disparity` and `uncertainty` from the pairs
    as given, `turned_*` from the pairs upside down, already turned back. All (B, 1, H, W):
    disparity in px (positive), uncertainty in [0, 1] (either the calibrated probability or the
    paper's U, the same kind in both). Returns the merged (disparity, uncertainty)."""
    agree = (disparity - turned_disparity).abs() < AGREEMENT_PX
    less_uncertain = torch.where(uncertainty <= turned_uncertainty, disparity, turned_disparity)
    merged = torch.where(agree, 0.5 * (disparity + turned_disparity), less_uncertain)
    return merged, 0.5 * (uncertainty + turned_uncertainty)
