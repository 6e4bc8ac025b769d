"""Pairs of mixed sizes in one batch (``StereoPredictor.predict_pairs``, behind ``predict_batch``):
each replicate-padded at the bottom and right to one shape, a multiple of INPUT_MULTIPLE, exactly as ``predict`` pads a
single pair, so each result equals ``predict`` on its pair alone up to float rounding; or, with
``two_pass="auto"``, one batch per size."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from crestereo_pp.model.network import padded_size

from .options import TwoPass
from .padding import Padding
from .prediction import Prediction, to_host
from .two_pass import two_pass_possible

ServeUncertainty = Callable[[Tensor, Tensor, Tensor], Tensor]
"""serve(raw, disparity, left): the uncertainty as served, (B, 1, H, W), from the paper's U
(B, 1, H, W), the disparity (B, 1, H, W) and the left images (B, 3, H, W)
(``StereoPredictor.served_uncertainty``)."""


def batch_two_pass(
    sizes: Sequence[tuple[int, ...]], two_pass: TwoPass, warm_started: bool, scale: float
) -> TwoPass | None:
    """How pairs of these (height, width) sizes run as one batch: the ``two_pass`` to run it with,
    or None where they run as one batch per size (``size_groups``): with ``two_pass="auto"``, cold
    and at scale 1, pairs of different sizes are decided per size, unless none of them is large
    enough for two passes (``two_pass_possible``: then one padded batch in one pass). With
    ``two_pass=True`` or a ``scale`` the resized passes would see the padding: ValueError where the
    sizes differ."""
    mixed = len(set(sizes)) > 1
    if mixed and two_pass == "auto" and not warm_started and scale == 1.0:
        return False if not any(two_pass_possible(*size) for size in sizes) else None
    if mixed and (two_pass is True or scale != 1.0):
        raise ValueError("pairs of different sizes can only be batched without two_pass or scale")
    return two_pass


def size_groups(sizes: Sequence[tuple[int, ...]]) -> list[list[int]]:
    """The indices of the pairs of each size, sizes in the order they first come."""
    return [[i for i, other in enumerate(sizes) if other == size] for size in dict.fromkeys(sizes)]


@dataclass(frozen=True)
class PaddedBatch:
    """Pairs of (possibly) different sizes as one (B, C, H, W) batch: each image padded at the
    bottom and right to the largest height and width, rounded up to multiples of INPUT_MULTIPLE
    where the sizes differ (``paddings``, one per pair)."""

    paddings: tuple[Padding, ...]

    @staticmethod
    def of(sizes: Sequence[tuple[int, ...]]) -> PaddedBatch:
        """The batch of pairs of these (height, width) sizes."""
        height = max(h for h, _ in sizes)
        width = max(w for _, w in sizes)
        if len(set(sizes)) > 1:
            height, width = padded_size(height), padded_size(width)
        return PaddedBatch(tuple(Padding(h, w, height, width) for h, w in sizes))

    @property
    def mixed(self) -> bool:
        """Whether the pairs differ in size (so that some are padded)."""
        return len({(padding.height, padding.width) for padding in self.paddings}) > 1

    def stack(self, images: Sequence[Tensor]) -> Tensor:
        """One (1, C, h, w) tensor per pair, each padded, as one (B, C, H, W) batch."""
        return torch.cat([padding.pad(image) for padding, image in zip(self.paddings, images, strict=True)])

    def served_per_pair(self, raw: Tensor, disparity: Tensor, left: Tensor, serve: ServeUncertainty) -> Tensor:
        """The uncertainty as served, (B, H, W), of a padded batch's paper's U `raw` (B, H, W):
        each pair's from its own maps and `left` image (disparity (B, H, W), left (B, 3, H, W)
        cropped to its size, borders as ``predict`` sees them) through `serve`; the padding keeps U."""
        served = raw.clone()
        for i, padding in enumerate(self.paddings):
            maps = (served[:, None], disparity[:, None], left)
            pair_raw, pair_disparity, pair_left = (padding.crop(x[i : i + 1]) for x in maps)
            served[i, : padding.height, : padding.width] = serve(pair_raw, pair_disparity, pair_left)[0, 0]
        return served

    def predictions(self, disparity: Tensor, uncertainty: Tensor) -> list[Prediction]:
        """Each pair's maps (numpy HxW, cropped to its size) from the batch's (B, H, W) disparity and
        uncertainty on the device, copied to the host in one transfer."""
        disparity_array, uncertainty_array = to_host(disparity, uncertainty)
        return [
            Prediction(
                np.ascontiguousarray(padding.crop(disparity_array[i])),
                np.ascontiguousarray(padding.crop(uncertainty_array[i])),
            )
            for i, padding in enumerate(self.paddings)
        ]
