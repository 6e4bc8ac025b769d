"""The host's classical steps on the network's answer, in order: the blend with OpenCV's SGBM
(``InferenceOptions.blend_sgbm``, ``inference.sgbm``), then the answer's edges
(``InferenceOptions.refine_edges``): its depth edges put where the colour edges are
(``inference.depth_edges``), then the strip along the image's left edge whose matches fall outside
the right image raised towards the surface beside it (``inference.border_strip``). Each pair's
disparity is refined where its maps reach the host (``batching.PairMaps``); the uncertainty stays
the network answer's."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from torch import Tensor

from .border_strip import raise_border_strip
from .depth_edges import refine_depth_edges
from .options import InferenceOptions
from .sgbm import blend_with_sgbm, host_rgb8

PairImages = tuple[Sequence[np.ndarray | Tensor], Sequence[np.ndarray | Tensor]]
"""The left and the right image of each pair, as ``predict_pairs`` took them (arrays, or
(1, 3|1, h, w) tensors)."""


@dataclass(frozen=True)
class HostRefinement:
    """The steps asked for (at least one), and the images of the pairs they read."""

    images: PairImages
    blend_sgbm: bool
    refine_edges: bool

    @staticmethod
    def of(images: PairImages, options: InferenceOptions) -> HostRefinement | None:
        """The refinement `options` ask for, None where they ask for the network's own answer."""
        if not (options.blend_sgbm or options.refine_edges):
            return None
        return HostRefinement(images, options.blend_sgbm, options.refine_edges)

    def __call__(self, index: int, disparity: np.ndarray) -> np.ndarray:
        """Pair `index`'s disparity (HxW float32 on the host, px), refined: a new array."""
        lefts, rights = self.images
        left = host_rgb8(lefts[index])
        if self.blend_sgbm:
            disparity = blend_with_sgbm(disparity, left, host_rgb8(rights[index]))
        if self.refine_edges:
            disparity = raise_border_strip(refine_depth_edges(disparity, left), left)
        return disparity
