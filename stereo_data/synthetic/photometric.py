"""Photometric changes of a rendered view (`PhotometricConfig`): blur, gamma, vignetting, gain,
offset, noise, JPEG."""

from __future__ import annotations

from functools import reduce

import cv2
import torch
import torch.nn.functional as F

from .config import PhotometricConfig
from .draw import Draw


def apply_photometric(image: torch.Tensor, cfg: PhotometricConfig, draw: Draw) -> torch.Tensor:
    """Randomly change one view: (B, 3, H, W) in [0, 255] -> the same, changed per sample."""
    batch = image.shape[0]
    per_sample = (batch, 1, 1, 1)
    sigma = torch.where(draw.chance(per_sample, cfg.blur_probability), draw.uniform(per_sample, *cfg.blur_sigma), 0.0)
    image = _gaussian_blur(image, sigma)
    gamma = draw.uniform(per_sample, *cfg.gamma)
    gain = draw.uniform(per_sample, *cfg.gain) * draw.uniform((batch, 3, 1, 1), *cfg.channel_gain)
    offset = draw.uniform(per_sample, *cfg.offset)
    if cfg.vignetting > 0:  # a lens: light falls off with the square of the distance from its centre
        gain = gain * _vignette(image.shape, draw.uniform(per_sample, 0, cfg.vignetting), draw)
    noise = draw.uniform(per_sample, *cfg.noise_sigma) * draw.normal(tuple(image.shape))
    image = 255 * (image / 255).clamp(0, 1).pow(gamma)
    image = (gain * image + offset + noise).clamp(0, 255)
    if cfg.jpeg_probability > 0:
        compressed = draw.chance((batch,), cfg.jpeg_probability)
        quality = draw.integers((batch,), *cfg.jpeg_quality)
        image = _jpeg(image, compressed, quality)
    return image


def _vignette(shape: torch.Size, strength: torch.Tensor, draw: Draw) -> torch.Tensor:
    """(B, 1, H, W) gains: 1 - strength * (r / r_corner)^2, r the distance from a centre drawn
    within 10 % of the frame's centre, strength (B, 1, 1, 1) the share lost at a corner."""
    batch, _, height, width = shape
    centre = draw.uniform((batch, 2, 1, 1), -0.1, 0.1) * torch.tensor([width, height], device=draw.device).view(
        1, 2, 1, 1
    )
    x = torch.arange(width, device=draw.device).view(1, 1, -1) - (width - 1) / 2 - centre[:, 0]
    y = torch.arange(height, device=draw.device).view(1, -1, 1) - (height - 1) / 2 - centre[:, 1]
    corner = (width**2 + height**2) / 4
    return (1 - strength[:, 0] * (x.square() + y.square()) / corner).clamp_min(0)[:, None]


def _jpeg(image: torch.Tensor, compressed: torch.Tensor, quality: torch.Tensor) -> torch.Tensor:
    """The views `compressed` (B,) saved as JPEG at `quality` (B,) and decoded again (on the host)."""
    if not compressed.any():
        return image
    result = image.clone()
    for index in torch.nonzero(compressed).flatten().tolist():
        rgb = image[index].permute(1, 2, 0).round().to(torch.uint8).cpu().numpy()
        ok, data = cv2.imencode(".jpg", rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(quality[index])])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        decoded = cv2.imdecode(data, cv2.IMREAD_COLOR)
        assert decoded is not None  # OpenCV just wrote it
        result[index] = torch.from_numpy(decoded[:, :, ::-1].copy()).to(image).permute(2, 0, 1)
    return result


def _gaussian_blur(image: torch.Tensor, sigma: torch.Tensor, radius: int = 3) -> torch.Tensor:
    """Separable Gaussian blur with per-sample sigma (B, 1, 1, 1) px; sigma 0 leaves the sample as is.
    Written as shifted sums (no convolution call) so that it is deterministic on every device."""
    offsets = torch.arange(-radius, radius + 1, device=image.device, dtype=image.dtype)
    weights = torch.exp(-offsets.square() / (2 * sigma[..., None].clamp_min(1e-3).square()))
    taps = (weights / weights.sum(-1, keepdim=True)).unbind(-1)  # taps x (B, 1, 1, 1)
    height, width = image.shape[-2:]
    padded = F.pad(image, (radius, radius, 0, 0), mode="replicate")
    image = reduce(torch.add, (w * padded[..., :, k : k + width] for k, w in enumerate(taps)))
    padded = F.pad(image, (0, 0, radius, radius), mode="replicate")
    return reduce(torch.add, (w * padded[..., k : k + height, :] for k, w in enumerate(taps)))
