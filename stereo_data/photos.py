"""Photographs used as surface textures by the procedural scenes (never as stereo pairs).

The photos are the single-view sample images bundled with scikit-image (`skimage.data`: people,
animals, objects, materials, text, astronomy and microscopy), so no download is needed. Its one
stereo pair (`stereo_motorcycle`) is not among them: no real stereo pair is ever trained on.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

PHOTOS = (
    "astronaut", "brick", "camera", "cat", "cell", "clock", "coffee", "coins", "grass", "gravel",
    "hubble_deep_field", "immunohistochemistry", "moon", "page", "retina", "rocket", "text",
)  # fmt: skip
"""Names of the `skimage.data` functions whose images are used."""


def load_photos(min_side: int, device: torch.device) -> list[torch.Tensor]:
    """Every photo of PHOTOS as a float32 (H, W, 3) RGB tensor in [0, 255] on `device`, grey ones
    repeated to three channels, enlarged where needed so that both sides are at least `min_side`."""
    try:
        import skimage.data
    except ImportError as error:
        raise RuntimeError(
            "photo textures need scikit-image: pip install 'crestereo-pp[train]' (or scikit-image)"
        ) from error
    photos = []
    for name in PHOTOS:
        image = np.asarray(getattr(skimage.data, name)())
        if image.ndim == 2:
            image = np.repeat(image[..., None], 3, axis=2)
        height, width = image.shape[:2]
        factor = max(1.0, min_side / min(height, width))
        if factor > 1.0:
            size = (max(min_side, round(width * factor)), max(min_side, round(height * factor)))
            image = cv2.resize(image, size, interpolation=cv2.INTER_CUBIC)
        photos.append(torch.from_numpy(np.ascontiguousarray(image[..., :3])).to(device, torch.float32))
    return photos
