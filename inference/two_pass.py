"""Two passes for large disparities: a pass at half resolution, then refinement at full
resolution from it; and the ``two_pass="auto"`` rule, which reads a quick quarter-resolution pass
of each pair (an eighth-resolution one where that cannot hold the range) and computes the pair in
two passes where its disparities are above LARGE_DISPARITY_PX, in one elsewhere, either way on
the pair enlarged up to 1.5x as far as the pass that finds the disparities still holds their
range, or shrunk where even two passes could not hold it."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from crestereo_pp.model.network import finest_stage_only
from crestereo_pp.model.upsample import resize_disparity

from .forward import Maps
from .options import StageCounts, TwoPass
from .scaling import maps_at, resize_images, shrink

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


QUICK_PASS_HOLDS_PX = 100.0
"""The quarter-resolution quick pass reads a pair's 99th percentile right (within 2 %) up to
about 150 px of what it sees (600 px at the pair's size), and then falls short: on SceneFlow A0032
enlarged 6x and 7x it read 569 and 507 px for 766 and 893. Where it reads more than this (px it
sees), an eighth-resolution pass reads the pair again, and its reading is taken: it was within
2 % of the truth from 196 to 893 px on three dev pairs enlarged 2x to 7x (MODEL_CARD.md, "Shrunk
where two passes cannot hold the range"), and costs a sixty-fourth of a pass."""


def quick_pass_percentile(
    left: Tensor, right: Tensor, iters: StageCounts, forward: PaddedForward, divisor: int
) -> Tensor:
    """(B,): the 99th percentile of each pair's disparity (px at H x W) in a pass of `forward`
    with `iters` on the (B, 3, H, W) batch shrunk to 1 / `divisor` of its size."""
    height, width = left.shape[-2:]
    small = (max(1, height // divisor), max(1, width // divisor))
    coarse, _ = forward(shrink(left, small), shrink(right, small), iters, None)
    return torch.quantile(coarse.flatten(1), 0.99, dim=1) * (width / small[1])


def large_disparity_percentile(left: Tensor, right: Tensor, iters: StageCounts, forward: PaddedForward) -> Tensor:
    """(B,): the 99th percentile of each pair's disparity (px at H x W) in a quick pass of
    `forward` with `iters` at quarter resolution of the (B, 3, H, W) batch, what
    ``two_pass="auto"`` decides by; for the pairs where that pass sees more than
    QUICK_PASS_HOLDS_PX, in a pass at eighth resolution (where it keeps QUICK_PASS_MIN_SIDE px a
    side)."""
    evidence = quick_pass_percentile(left, right, iters, forward, 4)
    beyond = evidence / 4 > QUICK_PASS_HOLDS_PX
    if beyond.any() and min(left.shape[-2:]) // 8 >= QUICK_PASS_MIN_SIDE:
        evidence[beyond] = quick_pass_percentile(left[beyond], right[beyond], iters, forward, 8)
    return evidence


ENLARGEMENTS = (1.25, 1.5)
"""The factors ``two_pass="auto"`` may enlarge a pair by (``auto_way``). Lite is more precise
where the network sees a pair larger, as long as the pass that finds the disparities still holds
their range: on the 16 dev pairs (torch fp32) every pair with a quick-pass 99th percentile under
75 px is better enlarged 1.5x than at its size, the three in two passes gain too, and the mean
over the pairs goes from bad-1 21.9 %, bad-2 10.9 %, EPE 1.26 px to 17.4 %, 8.9 %, 1.07 px
(MODEL_CARD.md, "Enlarged as far as the disparities allow"). A few fixed factors, so that a
camera's pairs meet a few shapes (each shape is a compile for OpenVINO and CUDA graphs)."""

ENLARGED_DISPARITY_PX = 100.0
"""``two_pass="auto"`` enlarges a pair only as far as its quick pass's 99th percentile, times the
factor, stays at most this (px of the image the network sees): the single pass's range, a little
above LARGE_DISPARITY_PX (dev pairs enlarged to 120-150 px got worse)."""

MAX_ENLARGED_PIXELS = 1_200_000
"""``two_pass="auto"`` enlarges a pair only as far as the network sees at most this many pixels
(a KITTI frame, 1242 x 375, at 1.5x: 1.05 M), so that enlarging costs at most 2.25x a pass and
large images are computed at their own size."""

AutoWay = tuple[bool, float]
"""How ``two_pass="auto"`` computes one pair: (two passes, enlargement factor); ``way_maps``."""


def largest_enlargement(height: int, width: int) -> float:
    """The largest factor ``two_pass="auto"`` may enlarge a ``height`` x ``width`` pair by, whatever
    its disparities: the largest of ENLARGEMENTS within MAX_ENLARGED_PIXELS where
    ``two_pass_possible``, else 1 (what a request costs at most: the service's cost model)."""
    if not two_pass_possible(height, width):
        return 1.0
    return max((factor for factor in ENLARGEMENTS if height * width * factor**2 <= MAX_ENLARGED_PIXELS), default=1.0)


SHRINK_ABOVE_PX = 140.0
"""``two_pass="auto"`` shrinks a pair it computes in two passes where the half-resolution pass
would see more than this (px: half the quick pass's 99th percentile). A pass misses disparities
beyond about 110-120 px on real pairs, about 130 on procedural ones (LARGE_DISPARITY_PX); a pair
computed smaller is found (``shrink_factor``). On dev pairs enlarged 3x (bicubic; 300-380 px)
this took EPE from 7.5-47 px to 2.6-11 px; just past 120 px, procedural scenes with disparities
to half their width lost (MODEL_CARD.md, "Shrunk where two passes cannot hold the range")."""

SHRINK_STEP = 0.125
"""Shrink factors are multiples of this, so that a camera's pairs meet a few shapes (each shape
is a compile for OpenVINO and CUDA graphs)."""

MIN_SHRUNK_SIDE = 384
"""A shrunk pair keeps at least this many px per side (its half-resolution pass 192): where the
disparities pass half the image's width, shrinking does not help (a procedural scene of 256x512
with disparities to 256 px went from 39 to 89 % bad-2 at 0.625x), and such a pair is computed at
its size."""


def shrink_factor(seen_px: float, height: int, width: int) -> float:
    """The factor ``two_pass="auto"`` shrinks a ``height`` x ``width`` pair by when its
    half-resolution pass would see ``seen_px`` (above SHRINK_ABOVE_PX): the one that brings that
    to about LARGE_DISPARITY_PX, LARGE_DISPARITY_PX / seen_px rounded to a multiple of SHRINK_STEP,
    no smaller than keeps MIN_SHRUNK_SIDE px a side (1: not shrunk, where the pair has fewer)."""
    factor = max(1, round(LARGE_DISPARITY_PX / seen_px / SHRINK_STEP)) * SHRINK_STEP
    keeps_side = math.ceil(MIN_SHRUNK_SIDE / min(height, width) / SHRINK_STEP) * SHRINK_STEP
    return min(1.0, max(factor, keeps_side))


def auto_way(
    evidence_px: float, height: int, width: int, resize: bool = True, large_px: float | None = None
) -> AutoWay:
    """How ``two_pass="auto"`` computes a ``height`` x ``width`` pair whose quick pass puts the
    99th percentile of its disparity at ``evidence_px``: two passes above ``large_px`` (default
    LARGE_DISPARITY_PX; another: the rule's measurement, ``evaluation.two_pass_rule``), else one.
    Where ``resize`` (not for a pair the caller shrank: ``scale`` < 1), the pair is enlarged by the
    largest of ENLARGEMENTS within ``largest_enlargement`` that keeps the range the pass finding
    the disparities sees within what one pass holds: in one pass the evidence times the factor
    within ENLARGED_DISPARITY_PX; in two, the half-resolution pass's (half of it) within
    LARGE_DISPARITY_PX. A pair in two passes whose half-resolution pass would see more than
    SHRINK_ABOVE_PX is shrunk instead (``shrink_factor``)."""
    two_passes = evidence_px > (LARGE_DISPARITY_PX if large_px is None else large_px)
    seen_px, limit_px = (evidence_px / 2, LARGE_DISPARITY_PX) if two_passes else (evidence_px, ENLARGED_DISPARITY_PX)
    if not resize:
        return two_passes, 1.0
    if two_passes and seen_px > SHRINK_ABOVE_PX:
        return two_passes, shrink_factor(seen_px, height, width)
    bound = largest_enlargement(height, width)
    fitting = [factor for factor in ENLARGEMENTS if factor <= bound and seen_px * factor <= limit_px]
    return two_passes, max(fitting, default=1.0)


def cold_maps(
    left: Tensor, right: Tensor, iters: StageCounts, two_pass: TwoPass, forward: PaddedForward, *, resize: bool
) -> Maps:
    """The maps of (B, 3, H, W) pairs without a warm start, each (B, 1, H, W), computed by
    `forward` with `iters`: one pass, two passes (the second refining at 1/4 only from a
    half-resolution one), or, with "auto", each pair the way ``auto_way`` gives for its
    ``large_disparity_percentile`` (one pass for all where ``two_pass_possible`` says the pairs are
    too small); `resize`: whether "auto" may enlarge or shrink them. The one place "auto" is decided."""
    if two_pass != "auto":
        return way_maps(left, right, iters, (two_pass, 1.0), forward)
    height, width = left.shape[-2:]
    if not two_pass_possible(height, width):
        return forward(left, right, iters, None)
    evidence = large_disparity_percentile(left, right, iters, forward)
    ways = [auto_way(value, height, width, resize=resize) for value in evidence.tolist()]
    if len(set(ways)) == 1:
        return way_maps(left, right, iters, ways[0], forward)
    disparity, uncertainty = torch.empty_like(left[:, :1]), torch.empty_like(left[:, :1])
    for way in set(ways):
        group = torch.tensor([pair_way == way for pair_way in ways], device=left.device)
        disparity[group], uncertainty[group] = way_maps(left[group], right[group], iters, way, forward)
    return disparity, uncertainty


def way_maps(left: Tensor, right: Tensor, iters: StageCounts, way: AutoWay, forward: PaddedForward) -> Maps:
    """The maps of (B, 3, H, W) pairs computed one ``AutoWay``: resized by its factor (the maps
    brought back to H x W), in one pass or in two."""
    two_passes, factor = way
    height, width = left.shape[-2:]
    if factor != 1.0:
        size = (round(height * factor), round(width * factor))
        enlarged = way_maps(resize_images(left, size), resize_images(right, size), iters, (two_passes, 1.0), forward)
        return maps_at(enlarged, height, width)
    if not two_passes:
        return forward(left, right, iters, None)
    init = half_resolution_start(
        left, right, lambda small_left, small_right: forward(small_left, small_right, iters, None)[0]
    )
    return forward(left, right, finest_stage_only(iters), init)
