"""The padding the network needs: images replicate-padded at the bottom and right to multiples of
INPUT_MULTIPLE (or to a batch's common shape), and the maps cropped back."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from torch import Tensor
from torch.nn import functional as F

from crestereo_pp.model.network import padded_size

T = TypeVar("T", Tensor, np.ndarray)


@dataclass(frozen=True)
class Padding:
    """Replicate padding of an image of (height, width) px on the bottom and right to
    (padded_height, padded_width), and the crop that takes a map of the padded image back."""

    height: int
    width: int
    padded_height: int
    padded_width: int

    @staticmethod
    def to_multiple(height: int, width: int) -> Padding:
        """The padding the network needs: to multiples of INPUT_MULTIPLE."""
        return Padding(height, width, padded_size(height), padded_size(width))

    def pad(self, x: Tensor) -> Tensor:
        """(B, C, height, width) -> (B, C, padded_height, padded_width), edges replicated."""
        if (self.padded_height, self.padded_width) == tuple(x.shape[-2:]):
            return x
        return F.pad(x, (0, self.padded_width - x.shape[-1], 0, self.padded_height - x.shape[-2]), mode="replicate")

    def crop(self, x: T) -> T:
        """A map of the padded image (..., padded_height, padded_width), tensor or array, cut back
        to (..., height, width)."""
        return x[..., : self.height, : self.width]
