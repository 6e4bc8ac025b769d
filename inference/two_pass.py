"""Two passes for large disparities: a pass at half resolution, then refinement at full
resolution from it; and the ``two_pass="auto"`` rule, which computes a pair in two passes only
where a quick quarter-resolution pass finds disparities above LARGE_DISPARITY_PX."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from crestereo_pp.model.network import finest_stage_only
from crestereo_pp.model.upsample import resize_disparity

from .forward import Maps
from .options import StageCounts, TwoPass
from .scaling import shrink

LARGE_DISPARITY_PX = 90.0
"""``two_pass="auto"`` computes a pair in two passes where the 99th percentile of its quick
quarter-resolution pass's disparity (``StereoPredictor.large_disparity_percentile``) is above this
(px of the image the network sees). The single pass of lite's weights misses disparities beyond
about 90-100 px on real pairs (on procedural ones beyond about 130), where starting from a
half-resolution pass finds them; below, the single pass keeps finer detail. Measured on the dev
pairs with ``python -m crestereo_pp.evaluation.two_pass_rule``."""

QUICK_PASS_MIN_SIDE = 48
"""``two_pass="auto"``'s quick pass at quarter resolution needs at least this many pixels per side
to measure anything: on 16 x 24 or 32 x 48 px it reads 99th-percentile disparities of 140-220 px
on pairs whose true disparity is 4-16 px (and would send them to two passes)."""

PaddedForward = Callable[[Tensor, Tensor, StageCounts, Tensor | None], Maps]
"""forward(left, right, iters, init): the maps, each (B, 1, H, W), of (B, 3, H, W) images of any
size with an optional (B, 1, H, W) start disparity (px); ``StereoPredictor.forward_padded`` with
its backend bound."""


def two_pass_possible(height: int, width: int) -> bool:
    """Whether ``two_pass="auto"`` considers two passes for a pair of this size (as the network
    sees it): where its quick pass at quarter resolution keeps at least QUICK_PASS_MIN_SIDE px per
    side (192 px and more); smaller pairs take one pass."""
    return min(height, width) // 4 >= QUICK_PASS_MIN_SIDE


def half_resolution_start(left: Tensor, right: Tensor, coarse: Callable[[Tensor, Tensor], Tensor]) -> Tensor:
    """The first of two passes: the (B, 1, H, W) disparity (px at H x W, positive) that
    ``coarse`` finds on the (B, 3, H, W) pair shrunk to half its size, resized back to H x W. The
    second pass refines it at full resolution (``init_disparity``), at inference with
    ``two_pass`` and in training with ``TrainConfig.two_pass_fraction``."""
    height, width = left.shape[-2:]
    half_size = (max(1, height // 2), max(1, width // 2))
    return resize_disparity(coarse(shrink(left, half_size), shrink(right, half_size)), height, width)


def large_disparity_percentile(left: Tensor, right: Tensor, iters: StageCounts, forward: PaddedForward) -> Tensor:
    """(B,): the 99th percentile of each pair's disparity (px at H x W) in a quick pass of
    `forward` with `iters` at quarter resolution of the (B, 3, H, W) batch, what
    ``two_pass="auto"`` decides by."""
    height, width = left.shape[-2:]
    quarter = (max(1, height // 4), max(1, width // 4))
    coarse, _ = forward(shrink(left, quarter), shrink(right, quarter), iters, None)
    return torch.quantile(coarse.flatten(1), 0.99, dim=1) * (width / quarter[1])


def cold_maps(left: Tensor, right: Tensor, iters: StageCounts, two_pass: TwoPass, forward: PaddedForward) -> Maps:
    """The maps of (B, 3, H, W) pairs without a warm start, each (B, 1, H, W), computed by
    `forward` with `iters`: one pass, two passes (the second refining at 1/4 only from a
    half-resolution one), or, with "auto", two passes for the pairs whose
    ``large_disparity_percentile`` is above LARGE_DISPARITY_PX and one for the others (one for all
    where ``two_pass_possible`` says the pairs are too small). The one place "auto" is decided."""
    if two_pass == "auto":
        if not two_pass_possible(*left.shape[-2:]):
            two_pass = False
        else:
            needs = large_disparity_percentile(left, right, iters, forward) > LARGE_DISPARITY_PX
            if not bool(needs.all()) and bool(needs.any()):
                disparity, uncertainty = torch.empty_like(left[:, :1]), torch.empty_like(left[:, :1])
                for group, two in ((needs, True), (~needs, False)):
                    disparity[group], uncertainty[group] = cold_maps(left[group], right[group], iters, two, forward)
                return disparity, uncertainty
            two_pass = bool(needs.all())
    if not two_pass:
        return forward(left, right, iters, None)
    init = half_resolution_start(
        left, right, lambda small_left, small_right: forward(small_left, small_right, iters, None)[0]
    )
    return forward(left, right, finest_stage_only(iters), init)
