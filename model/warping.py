"""Warping of the right feature map into the left view (paper eqs. 2, 3 and 5).

Coordinates are in pixels of the feature map, x to the right, y down. A left pixel at x with
disparity d (positive) matches the right pixel at x - d. All sampling is bilinear with zeros
outside the map, through ``torch.nn.functional.grid_sample`` (no torchvision, no custom kernels).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from .convolution import input_response

KERNEL_POINTS = 9
"""K: the 3x3 sampling points of the content-aware warp, row-major (ky, kx) in {-1,0,1}^2."""


def pixel_grid(height: int, width: int, like: Tensor) -> tuple[Tensor, Tensor]:
    """Pixel-centre coordinates: xs (1,1,1,W) and ys (1,1,H,1), float32 on ``like``'s device."""
    # float32 whatever `like` is: bf16 cannot hold pixel positions above 256 exactly
    xs = torch.arange(width, device=like.device, dtype=torch.float32).view(1, 1, 1, width)
    ys = torch.arange(height, device=like.device, dtype=torch.float32).view(1, 1, height, 1)
    return xs, ys


def kernel_offsets(like: Tensor) -> tuple[Tensor, Tensor]:
    """kx, ky of the K = 9 points, each shaped (1,1,9,1,1) for broadcasting over (B,G,K,h,w)."""
    steps = torch.arange(-1, 2, device=like.device, dtype=torch.float32)
    ky, kx = torch.meshgrid(steps, steps, indexing="ij")
    return kx.reshape(1, 1, KERNEL_POINTS, 1, 1), ky.reshape(1, 1, KERNEL_POINTS, 1, 1)


def sampling_grid(x: Tensor, y: Tensor) -> Tensor:
    """grid_sample's grid: x and y (same shape S) as pairs, shape (*S, 2).

    In eager torch this is ``torch.stack``. In an exported graph it is ``x * [1, 0] + y * [0, 1]``,
    the same numbers exactly: OpenVINO runs a concatenation on the last axis with its slow reference
    kernel (10 % of lite's time at 384x1248) and this sum as one fused elementwise kernel, while
    in eager torch the sum is about 10x slower than the stack."""
    if not torch.compiler.is_exporting():
        return torch.stack((x, y), dim=-1)
    unit_x = torch.tensor([1.0, 0.0], dtype=x.dtype, device=x.device)
    unit_y = torch.tensor([0.0, 1.0], dtype=y.dtype, device=y.device)
    return x.unsqueeze(-1) * unit_x + y.unsqueeze(-1) * unit_y


def deformable_sample(feature: Tensor, x: Tensor, y: Tensor) -> Tensor:
    """Sample a feature map at per-group, per-point positions.

    Args:
        feature: (B, C, H, W) map to sample; its C channels form G equal groups.
        x, y: (B, G, K, h, w) sampling positions in pixels of ``feature``; channel c uses the
            positions of its group c // (C / G). Positions outside the map read zeros.
    Returns:
        (B, C, K, h, w): feature[b, c] bilinearly interpolated at (x, y)[b, c // (C/G), k].
    """
    b, c, height, width = feature.shape
    groups, points, h, w = x.shape[1:]
    # Pixels in grid_sample's [-1, 1] frame (align_corners: pixel x is 2x / (W - 1) - 1), written as
    # tensor arithmetic so that an export with symbolic sizes keeps it graph ops.
    grid = sampling_grid(2 * x / max(width - 1, 1) - 1, 2 * y / max(height - 1, 1) - 1)
    grid = grid.view(b * groups, points * h, w, 2)
    sampled = F.grid_sample(
        feature.reshape(b * groups, c // groups, height, width),
        grid,
        mode="bilinear",
        padding_mode="zeros",
        align_corners=True,
    )
    return sampled.view(b, c, points, h, w)


def bilinear_warp(right: Tensor, disparity: Tensor) -> Tensor:
    """Plain warp (paper eq. 2 with a single point): out(x, y) = right(x - d(x, y), y).

    Args:
        right: (B, C, H, W) right-view features.
        disparity: (B, 1, H, W) positive disparity in pixels of this map.
    Returns:
        (B, C, H, W) right features aligned to the left view.
    """
    height, width = right.shape[-2:]
    xs, ys = pixel_grid(height, width, right)
    x = (xs - disparity).unsqueeze(2)  # (B, 1, 1, H, W)
    y = ys.expand_as(disparity).unsqueeze(2)
    return deformable_sample(right, x, y).squeeze(2)


def neighbour_disparities(disparity: Tensor) -> Tensor:
    """d(p + k) for the 9 points k around every pixel: (B,1,H,W) -> (B,1,9,H,W), border replicated."""
    b, _, height, width = disparity.shape
    padded = F.pad(disparity, (1, 1, 1, 1), mode="replicate")
    return F.unfold(padded, kernel_size=3).view(b, 1, KERNEL_POINTS, height, width)


class OffsetNet(nn.Module):
    """CNN[F_L, S(F_R, d), d] of paper eq. 5: three 3x3 convs with LeakyReLU(0.1) between.

    The last conv is zero-initialised, so training starts from the plain deformable warp.
    Output: (B, G, 9, h, w) horizontal offsets in pixels, bounded by ``max_offset * tanh``.
    """

    def __init__(self, feature_dim: int, hidden: int, groups: int, max_offset: float) -> None:
        super().__init__()
        self.groups = groups
        self.max_offset = max_offset
        self.layers = nn.Sequential(
            nn.Conv2d(2 * feature_dim + 1, hidden, 3, padding=1),
            nn.LeakyReLU(0.1, inplace=True),
            nn.Conv2d(hidden, hidden, 3, padding=1),
            nn.LeakyReLU(0.1, inplace=True),
            nn.Conv2d(hidden, groups * KERNEL_POINTS, 3, padding=1),
        )
        head = self.layers[-1]
        assert isinstance(head, nn.Conv2d) and head.bias is not None
        nn.init.zeros_(head.weight)
        nn.init.zeros_(head.bias)

    @property
    def first_conv(self) -> nn.Conv2d:
        """The conv that reads [F_L, S(F_R, d), d]."""
        first = self.layers[0]
        assert isinstance(first, nn.Conv2d)
        return first

    def left_response(self, left: Tensor) -> Tensor:
        """The first conv's response to F_L (B, C, h, w) with its bias: (B, hidden, h, w),
        constant over a stage's iterations (computed once per stage)."""
        return input_response(self.first_conv, left, 0, True)

    def forward(self, left_response: Tensor, coarse_warp: Tensor, disparity: Tensor) -> Tensor:
        """left_response: ``left_response(F_L)``; coarse_warp: S(F_R, d) (B, C, h, w); disparity
        (B, 1, h, w) pixels. Returns the offsets (B, G, 9, h, w) in pixels."""
        own = input_response(self.first_conv, torch.cat((coarse_warp, disparity), dim=1), coarse_warp.shape[1], False)
        raw = self.layers[1:](left_response + own)
        b, _, h, w = raw.shape
        return (self.max_offset * torch.tanh(raw)).view(b, self.groups, KERNEL_POINTS, h, w)


class ContentAwareWarp(nn.Module):
    """Content-aware warping (paper eq. 3), realised as a deformable 3x3 convolution:

        out(p) = bias + sum_k W_k · F_R(p + k - d(p + k) + o(p, k))

    over the UNWARPED right feature, with learned weights W (C_out x C_in per point, bias, no
    modulation) and learned horizontal offsets o, one set per offset group. When the previous
    iteration's uncertainty U is given, the offsets are U · o (paper eq. 5, the ``ugac`` mode).
    With o = 0 and W_k = identity / 9 this is the 3x3 mean of the plain bilinear warp (eq. 2).
    """

    def __init__(self, feature_dim: int, offset_hidden: int, groups: int, max_offset: float) -> None:
        super().__init__()
        self.offsets = OffsetNet(feature_dim, offset_hidden, groups, max_offset)
        conv = nn.Conv2d(feature_dim, feature_dim, 3)  # holds the default-initialised W and bias
        assert conv.bias is not None
        self.weight = nn.Parameter(conv.weight.detach().clone())  # (C_out, C_in, 3, 3)
        self.bias = nn.Parameter(conv.bias.detach().clone())  # (C_out,)

    def left_response(self, left: Tensor) -> Tensor:
        """The per-stage constant of the offset CNN from the left features (B, C, h, w)."""
        return self.offsets.left_response(left)

    def forward(self, left_response: Tensor, right: Tensor, disparity: Tensor, uncertainty: Tensor | None) -> Tensor:
        """left_response: ``left_response(F_L)`` of this scale; right: (B,C,h,w) features;
        disparity: (B,1,h,w) pixels; uncertainty: (B,1,h,w) in [0,1] or None (unscaled offsets).
        Returns the warped right feature (B,C,h,w)."""
        offsets = self.offsets(left_response, bilinear_warp(right, disparity), disparity)
        if uncertainty is not None:
            offsets = offsets * uncertainty.unsqueeze(2)
        return self.deform(right, disparity, offsets)

    def deform(self, right: Tensor, disparity: Tensor, offsets: Tensor) -> Tensor:
        """The deformable convolution itself, for given offsets (B,G,9,h,w) in pixels."""
        b, c, h, w = right.shape
        xs, ys = pixel_grid(h, w, right)
        kx, ky = kernel_offsets(right)
        x = xs + kx - neighbour_disparities(disparity) + offsets  # (B, G, 9, h, w)
        y = (ys + ky).expand_as(x)
        sampled = deformable_sample(right, x, y).reshape(b, c * KERNEL_POINTS, h * w)
        # sum over (c_in, k) of W * sampled: a 1x1 conv1d, which (unlike a broadcast matmul) needs
        # no transposed copy of the (B, C*9, h*w) samples
        out = F.conv1d(sampled, self.weight.reshape(c, c * KERNEL_POINTS, 1), self.bias)
        return out.view(b, c, h, w)
