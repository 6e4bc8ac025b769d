"""The scenes' texture banks: 1/f noise, dead leaves, patterns and photo crops, periodic where
procedural."""

from __future__ import annotations

import math

import torch

from .config import SceneConfig
from .draw import Draw
from .hard_cases import REPETITIVE_TEXTURES, repetitive_period_texels


def texture_bank(batch_size: int, cfg: SceneConfig, draw: Draw, photos: list[torch.Tensor]) -> torch.Tensor:
    """(B, K, T, T, 3) textures (procedural ones periodic), each standardised to zero mean and
    unit std.

    Slots [0, noise) are 1/f^alpha noise, then dead leaves, then patterns, then photo crops;
    leaves and patterns carry some of their slot's noise on top, so that no texture is perfectly
    clean. Photo crops wrap with a seam, which both views show alike. With repetitive_probability,
    REPETITIVE_TEXTURES clean patterns follow (after texture_count slots), repeating every
    `repetitive_period_texels` texels along u.
    """
    size, count = cfg.texture_size, cfg.texture_count
    procedural = count - cfg.photo_textures
    noise = _standardise(_power_law_noise((batch_size, procedural), size, draw))
    structured = torch.cat(
        [
            _dead_leaves((batch_size, cfg.leaves_textures), size, draw),
            _patterns((batch_size, cfg.pattern_textures), size, draw),
        ],
        dim=1,
    )
    mix = draw.uniform((batch_size, procedural - cfg.noise_textures, 1, 1, 1), 0.0, 0.3)
    textured = _standardise(structured) + mix * noise[:, cfg.noise_textures :]
    parts = [noise[:, : cfg.noise_textures], textured]
    if cfg.photo_textures:
        parts.append(_standardise(_photo_crops((batch_size, cfg.photo_textures), size, draw, photos)))
    if cfg.repetitive_probability > 0:
        period = repetitive_period_texels(size)
        repetitive = _patterns((batch_size, REPETITIVE_TEXTURES), size, draw, period=(period, period), turn=0.0)
        parts.append(_standardise(repetitive))
    return _standardise(torch.cat(parts, dim=1))


def _photo_crops(shape: tuple[int, int], size: int, draw: Draw, photos: list[torch.Tensor]) -> torch.Tensor:
    """(B, K, T, T, 3) random T x T crops of random photos, each turned by a random multiple of
    90 degrees, mirrored at random and with its colour channels in a random order."""
    count = shape[0] * shape[1]
    which = draw.integers((count,), 0, len(photos) - 1).tolist()
    corner = draw.uniform((count, 2), 0.0, 1.0).tolist()
    turns = draw.integers((count,), 0, 3).tolist()
    mirror = draw.chance((count,), 0.5).tolist()
    channels = torch.argsort(draw.uniform((count, 3), 0.0, 1.0), dim=1)
    crops = []
    for n in range(count):
        photo = photos[which[n]]
        top = int(corner[n][0] * (photo.shape[0] - size))
        left = int(corner[n][1] * (photo.shape[1] - size))
        crop = torch.rot90(photo[top : top + size, left : left + size], turns[n], dims=(0, 1))
        crop = crop.flip(1) if mirror[n] else crop
        crops.append(crop[..., channels[n]])
    return torch.stack(crops).view(*shape, size, size, 3)


def _standardise(textures: torch.Tensor) -> torch.Tensor:
    """Zero mean per channel, unit std over all channels, per texture of (B, K, T, T, 3)."""
    centred = textures - textures.mean(dim=(2, 3), keepdim=True)
    return centred / centred.std(dim=(2, 3, 4), keepdim=True).clamp_min(1e-6)


def _power_law_noise(shape: tuple[int, int], size: int, draw: Draw) -> torch.Tensor:
    """(B, K, T, T, 3) periodic noise with amplitude spectrum 1/f^alpha, alpha in [0.4, 1.8]: low
    alpha gives fine detail, ~1 natural-photo statistics, high alpha smooth gradients. Colour is a
    shared luminance field plus weaker independent chroma fields."""
    device = draw.device
    fy = torch.fft.fftfreq(size, device=device).view(-1, 1)
    fx = torch.fft.rfftfreq(size, device=device).view(1, -1)
    frequency = torch.sqrt(fx.square() + fy.square())
    frequency[0, 0] = math.inf  # no DC
    alpha = draw.uniform((*shape, 1, 1, 1), 0.4, 1.8)
    amplitude = frequency.pow(-alpha)
    spectrum_shape = (*shape, 4, size, size // 2 + 1)
    spectrum = torch.complex(draw.normal(spectrum_shape), draw.normal(spectrum_shape)) * amplitude
    fields = torch.fft.irfft2(spectrum, s=(size, size))  # (B, K, 4, T, T)
    fields = fields / fields.std(dim=(3, 4), keepdim=True).clamp_min(1e-12)
    saturation = draw.uniform((*shape, 1, 1, 1), 0.0, 0.7)
    rgb: torch.Tensor = fields[:, :, :1] + saturation * fields[:, :, 1:]
    return rgb.permute(0, 1, 3, 4, 2)


def _texel_grid(size: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    coordinates = torch.arange(size, device=device, dtype=torch.float32)
    return coordinates.view(1, 1, 1, -1), coordinates.view(1, 1, -1, 1)  # u (columns), v (rows)


def _dead_leaves(shape: tuple[int, int], size: int, draw: Draw, discs: int = 64) -> torch.Tensor:
    """(B, K, T, T, 3) dead leaves: discs of random colours painted over each other (wrapping),
    radii log-uniform on [2, T/3] texels, enough of them to cover nearly all of the texture."""
    u, v = _texel_grid(size, draw.device)
    centre_u = draw.uniform((discs, *shape, 1, 1), 0, size).unbind(0)
    centre_v = draw.uniform((discs, *shape, 1, 1), 0, size).unbind(0)
    radius = draw.log_uniform((discs, *shape, 1, 1), 2.0, max(size / 3, 2.0))
    top = torch.zeros((*shape, size, size), dtype=torch.long, device=draw.device)  # 0: no disc yet
    for disc in range(discs):
        du = torch.remainder(u - centre_u[disc] + size / 2, size) - size / 2
        dv = torch.remainder(v - centre_v[disc] + size / 2, size) - size / 2
        top = torch.where(du.square() + dv.square() < radius[disc].square(), disc + 1, top)
    colors = draw.normal((*shape, discs + 1, 3))  # entry 0 is the ground under all discs
    return torch.gather(colors, 2, top.flatten(2)[..., None].expand(-1, -1, -1, 3)).view(*shape, size, size, 3)


def _patterns(
    shape: tuple[int, int],
    size: int,
    draw: Draw,
    period: tuple[float, float] = (3.0, 40.0),
    turn: float = math.pi,
) -> torch.Tensor:
    """(B, K, T, T, 3) two-colour periodic patterns: stripes, checkers, grid lines or dots, with
    periods log-uniform in `period` texels, turned from repeating along u by up to `turn` radians
    (integer wave vectors keep them periodic in T)."""
    u, v = _texel_grid(size, draw.device)
    period_texels = draw.log_uniform(shape, *period)
    orientation = draw.uniform(shape, 0, turn)
    kx = torch.round(size / period_texels * torch.cos(orientation))
    ky = torch.round(size / period_texels * torch.sin(orientation))
    kx = torch.where((kx == 0) & (ky == 0), 1.0, kx)
    kx, ky = kx[..., None, None], ky[..., None, None]
    phase_a, phase_b = (draw.uniform((*shape, 1, 1), 0, 2 * math.pi) for _ in range(2))
    cos_a = torch.cos(2 * math.pi * (kx * u + ky * v) / size + phase_a)
    cos_b = torch.cos(2 * math.pi * (-ky * u + kx * v) / size + phase_b)
    # (value, threshold) per kind: stripes with a random duty cycle, checkers, thin grid lines, dots.
    values = torch.stack([cos_a, cos_a * cos_b, torch.maximum(cos_a, cos_b), (cos_a + cos_b) / 2], 2)
    thresholds = torch.stack(
        [
            draw.uniform(shape, -0.5, 0.5),
            torch.zeros(shape, device=draw.device),
            draw.uniform(shape, 0.5, 0.9),
            draw.uniform(shape, 0.2, 0.8),
        ],
        dim=2,
    )
    kind = draw.integers((*shape, 1), 0, 3)
    value = torch.gather(values, 2, kind[..., None, None].expand(*shape, 1, size, size))[:, :, 0]
    threshold = torch.gather(thresholds, 2, kind)[..., None]
    sharpness = draw.log_uniform((*shape, 1, 1), 2.0, 30.0)
    mask = torch.sigmoid(sharpness * (value - threshold))[..., None]
    first, second = draw.normal((*shape, 1, 1, 3)), draw.normal((*shape, 1, 1, 3))
    return first + (second - first) * mask
