"""What a prediction takes and gives: images in (arrays or tensors, onto the predictor's device),
and maps out (``Prediction`` on the host, ``TensorPrediction`` on the device; the one copy from
the device to the host is ``batching.PairMaps.on_host``)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from crestereo_pp.stereo_data.formats import check_pixel_values


class Prediction(NamedTuple):
    """Disparity (positive, pixels of the left image) and uncertainty (in [0, 1]) maps of a pair
    given as arrays (``predict``, ``predict_batch``): float32 numpy HxW, on the host."""

    disparity: np.ndarray
    uncertainty: np.ndarray


class TensorPrediction(NamedTuple):
    """The maps of ``Prediction`` for pairs given as tensors (``predict``): float32 torch
    (B, H, W) on the predictor's device."""

    disparity: Tensor
    uncertainty: Tensor


def as_image_batch(image: np.ndarray | Tensor, device: torch.device) -> Tensor:
    """An image as (B, 3, H, W) float32 in [0, 255] on ``device``.

    Arrays: HxWx3 RGB, HxWx4 (alpha dropped), HxW or HxWx1 grayscale (replicated to RGB);
    uint8 as is, uint16 scaled to [0, 255], other numbers taken as [0, 255] (ValueError where they
    cannot be: ``check_pixel_values``). Tensors: (B, 3|1, H, W), taken as [0, 255] unchecked.
    """
    if isinstance(image, np.ndarray):
        array = image[..., None] if image.ndim == 2 else image
        if array.ndim != 3 or array.shape[2] not in (1, 3, 4):
            raise ValueError(f"expected an HxW, HxWx1, HxWx3 or HxWx4 image, got shape {image.shape}")
        if array.dtype not in (np.uint8, np.uint16):
            check_pixel_values(array)
        scale = 255.0 / 65535.0 if array.dtype == np.uint16 else 1.0
        # writable: torch warns about every read-only array (decoded from bytes, memory-mapped)
        pixels = np.require(array[..., :3], requirements=("C", "W"))
        batch = torch.from_numpy(pixels).to(device).permute(2, 0, 1)[None]
        batch = batch.float() * scale
    elif isinstance(image, Tensor):
        if image.ndim != 4 or image.shape[1] not in (1, 3):
            raise ValueError(f"expected a (B, 3, H, W) or (B, 1, H, W) tensor, got {tuple(image.shape)}")
        batch = image.to(device=device, dtype=torch.float32)
    else:
        raise TypeError(f"expected a numpy array or a torch tensor, got {type(image).__name__}")
    return batch.expand(-1, 3, -1, -1) if batch.shape[1] == 1 else batch


GREY_WEIGHTS = np.array([0.299, 0.587, 0.114], np.float32)
"""The luma weights of R, G and B (ITU-R BT.601, as OpenCV's RGB2GRAY) that turn colour into grey."""


def is_grey(image: np.ndarray) -> bool:
    """Whether an image array as ``as_image_batch`` takes it holds no colour: HxW, HxWx1, or
    every pixel's R, G and B equal (a grey image stored as colour)."""
    if image.ndim == 2 or image.shape[2] == 1:
        return True
    return bool(np.array_equal(image[..., 0], image[..., 1]) and np.array_equal(image[..., 1], image[..., 2]))


def same_colour(left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pair as the network should see it: where one image is grey (``is_grey``) and the other
    in colour, the colour one made grey too (HxW, its dtype kept; ``GREY_WEIGHTS``), so that
    matching pixels look alike (lite on Middlebury Teddy, a colour left and a grey right: bad-2
    8.9 %, both grey or both colour: 6.6 %); else the pair as given."""
    grey_left, grey_right = is_grey(left), is_grey(right)
    if grey_left == grey_right:
        return left, right
    return (left, _to_grey(right)) if grey_left else (_to_grey(left), right)


def _to_grey(image: np.ndarray) -> np.ndarray:
    """An HxWx3|4 array as HxW grey (alpha dropped), in its dtype (integers rounded)."""
    grey: np.ndarray = image[..., :3].astype(np.float32) @ GREY_WEIGHTS
    if np.issubdtype(image.dtype, np.integer):
        grey = np.rint(grey)
    return grey.astype(image.dtype)


def image_size(image: np.ndarray | Tensor) -> tuple[int, int]:
    """(height, width) of an image as ``as_image_batch`` takes it: an HxW[xC] array or a
    (B, C, H, W) tensor."""
    if isinstance(image, np.ndarray):
        if image.ndim not in (2, 3):
            raise ValueError(f"expected an HxW, HxWx1, HxWx3 or HxWx4 image, got shape {image.shape}")
        return image.shape[0], image.shape[1]
    if isinstance(image, Tensor):
        return image.shape[-2], image.shape[-1]
    raise TypeError(f"expected a numpy array or a torch tensor, got {type(image).__name__}")
