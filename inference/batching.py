"""Pairs of mixed sizes in one batch (``StereoPredictor.predict_pairs``): pairs of one padded shape
(a multiple of INPUT_MULTIPLE), each replicate-padded at the bottom and right to it exactly as the
network pads a single pair, so each result equals the pair computed alone up to float rounding;
pairs of other padded shapes in other batches, and with ``two_pass="auto"`` one batch per size
(``batch_groups``). A pair padded further than alone would not get its own answer: the network's
receptive field reaches across the image, and Middlebury Tsukuba (288x384) in one pass beside
Teddy padded to 384x480 moved by 0.09 px at the median, 1.9 px at the 99th percentile (bad-2 5.61
-> 5.80 %)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from crestereo_pp.model.network import padded_size

from .options import TwoPass
from .padding import Padding
from .prediction import Prediction, TensorPrediction
from .refinement import HostRefinement
from .row_alignment import RowOffset
from .two_pass import two_pass_possible

ServeUncertainty = Callable[[Tensor, Tensor, Tensor, Tensor], Tensor]
"""serve(raw, disparity, left, right): the uncertainty as served, (B, 1, H, W), from the paper's U
(B, 1, H, W), the disparity (B, 1, H, W) and the left and right images (B, 3, H, W)
(``StereoPredictor.served_uncertainty``)."""


def batch_groups(
    sizes: Sequence[tuple[int, int]], two_pass: TwoPass, warm_started: bool, scale: float
) -> list[tuple[list[int], TwoPass]]:
    """How pairs of these (height, width) sizes run: the batches (the indices of their pairs, in
    order) and the ``two_pass`` each runs with. Pairs of one padded shape (each size rounded up to
    a multiple of INPUT_MULTIPLE, as the network pads a pair alone) run as one batch, so that each
    gets the maps it gets alone; with ``two_pass="auto"``, cold and at scale 1, pairs of different
    sizes are decided per size (one batch per size, sizes in the order they first come), unless
    none of them is large enough for two passes (``two_pass_possible``: then one pass, batched by
    padded shape). With ``two_pass=True`` or a ``scale`` the resized passes would see the
    padding: ValueError where the sizes differ."""
    if len(set(sizes)) == 1:
        return [(list(range(len(sizes))), two_pass)]
    if two_pass == "auto" and not warm_started and scale == 1.0:
        if any(two_pass_possible(*size) for size in sizes):
            return [(group, "auto") for group in _indices_by(sizes)]
        two_pass = False
    elif two_pass is True or scale != 1.0:
        raise ValueError("pairs of different sizes can only be batched without two_pass or scale")
    shapes = [(padded_size(height), padded_size(width)) for height, width in sizes]
    return [(group, two_pass) for group in _indices_by(shapes)]


def _indices_by(keys: Sequence[tuple[int, int]]) -> list[list[int]]:
    """The indices of equal keys, one list per key, keys in the order they first come."""
    return [[i for i, other in enumerate(keys) if other == key] for key in dict.fromkeys(keys)]


@dataclass(frozen=True)
class PaddedBatch:
    """Pairs of (possibly) different sizes as one (B, C, H, W) batch: each image padded at the
    bottom and right to the largest height and width, rounded up to multiples of INPUT_MULTIPLE
    where the sizes differ (``paddings``, one per pair)."""

    paddings: tuple[Padding, ...]

    @staticmethod
    def of(sizes: Sequence[tuple[int, int]]) -> PaddedBatch:
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

    def upside_down(self, batch: Tensor) -> Tensor:
        """The (B, C, H, W) `batch` with each pair's rows reversed within its own size, padded again
        as ``stack`` pads it: the stack of the pairs upside down, and, applied to their maps, those
        maps turned back (``inference.flip``)."""
        if not self.mixed:
            return batch.flip(-2)
        return self.stack([padding.crop(batch[i : i + 1]).flip(-2) for i, padding in enumerate(self.paddings)])

    def served(self, raw: Tensor, disparity: Tensor, left: Tensor, right: Tensor, serve: ServeUncertainty) -> Tensor:
        """The uncertainty as served, (B, 1, H, W), of the batch's paper's U `raw` (B, 1, H, W)
        through `serve`: each pair's from its own maps and images (disparity (B, 1, H, W), `left`
        and `right` (B, 3, H, W)) cropped to its size, borders as the pair alone has them; the
        padding keeps U."""
        if not self.mixed:
            return serve(raw, disparity, left, right)
        served = raw.clone()
        for i, padding in enumerate(self.paddings):
            pair_maps = (padding.crop(x[i : i + 1]) for x in (raw, disparity, left, right))
            served[i : i + 1, :, : padding.height, : padding.width] = serve(*pair_maps)
        return served


@dataclass(frozen=True)
class PairMaps:
    """The maps of pairs computed together (``StereoPredictor.predict_pairs``), on the device:
    for each batch that ran, the indices of its pairs (in the order given), its padding and its
    maps stacked as one (2, B, H, W) tensor (disparity, uncertainty). With a `refinement`, each
    pair's disparity is refined on its way out (``inference.refinement``: the blend with SGBM, the
    edges): host work, done where the maps reach the host. row_offsets: where the right images'
    rows were measured (``InferenceOptions.align_rows``), each pair's offset in the order given
    (None for a pair given as tensors, or with too little texture to measure); else empty."""

    batches: tuple[tuple[tuple[int, ...], PaddedBatch, Tensor], ...]
    refinement: HostRefinement | None = None
    row_offsets: tuple[RowOffset | None, ...] = ()

    @staticmethod
    def of(
        batches: Sequence[tuple[Sequence[int], PaddedBatch, Tensor, Tensor]],
        refinement: HostRefinement | None = None,
        row_offsets: Sequence[RowOffset | None] = (),
    ) -> PairMaps:
        """From each batch's pair indices, padding, and (B, H, W) disparity and uncertainty, the
        refinement of their answers, if any, and the pairs' measured row offsets."""
        return PairMaps(
            tuple(
                (tuple(indices), batch, torch.stack((disparity, uncertainty)))
                for indices, batch, disparity, uncertainty in batches
            ),
            refinement,
            tuple(row_offsets),
        )

    def on_host(self) -> list[Prediction]:
        """Each pair's maps as numpy HxW arrays, copied to the host once per batch (the stack,
        (2, H, W) for a batch of one pair): the only device-to-host transfer of a prediction (and of
        the refinement, for images given as arrays)."""
        results: dict[int, Prediction] = {}
        for indices, batch, maps in self.batches:
            host = maps[:, 0].cpu().numpy()[:, None] if maps.shape[1] == 1 else maps.cpu().numpy()
            for i, (index, padding) in enumerate(zip(indices, batch.paddings, strict=True)):
                disparity, uncertainty = (np.ascontiguousarray(padding.crop(host[k, i])) for k in (0, 1))
                results[index] = Prediction(self._refined(index, disparity), uncertainty)
        return [results[i] for i in range(len(results))]

    def on_device(self) -> TensorPrediction:
        """The maps of pairs of one size computed as one batch (``predict`` of a tensor batch),
        (B, H, W) each, on the device as they are; refined (``inference.refinement``), each pair's
        disparity and images are copied to the host and the refined disparity back."""
        if len(self.batches) != 1 or self.batches[0][1].mixed:
            raise ValueError("on_device takes the maps of pairs of one size, computed as one batch")
        indices, _, maps = self.batches[0]
        disparity = maps[0]
        if self.refinement is not None:
            refined = [
                self.refinement(index, pair.cpu().numpy()) for index, pair in zip(indices, disparity, strict=True)
            ]
            disparity = torch.from_numpy(np.stack(refined)).to(disparity.device)
        return TensorPrediction(disparity, maps[1])

    def _refined(self, index: int, disparity: np.ndarray) -> np.ndarray:
        """Pair `index`'s disparity (HxW, on the host), refined where asked."""
        return disparity if self.refinement is None else self.refinement(index, disparity)
