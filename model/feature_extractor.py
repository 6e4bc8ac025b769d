"""Feature extraction module (FEM), shared by the left and right views (paper sec. 3.1)."""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional as F


class ResidualBlock(nn.Module):
    """Two 3x3 convs with instance norm and ReLU, plus a 1x1 conv + norm shortcut."""

    def __init__(self, in_channels: int, out_channels: int, stride: int = 1) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1)
        self.conv2 = nn.Conv2d(out_channels, out_channels, 3, padding=1)
        self.shortcut = nn.Conv2d(in_channels, out_channels, 1, stride=stride)
        self.norm1 = nn.InstanceNorm2d(out_channels)
        self.norm2 = nn.InstanceNorm2d(out_channels)
        self.norm_shortcut = nn.InstanceNorm2d(out_channels)

    def forward(self, x: Tensor) -> Tensor:
        y = F.relu(self.norm1(self.conv1(x)))
        y = F.relu(self.norm2(self.conv2(y)))
        return F.relu(self.norm_shortcut(self.shortcut(x)) + y)


class FeatureExtractor(nn.Module):
    """Image (B,3,H,W) normalised to [-1,1] -> features (B,C,H/4,W/4).

    conv 7x7 stride 2 + instance norm + ReLU, then three stages of two residual blocks
    (1/2, stride 2 to 1/4, 1/4), then a 1x1 conv to C channels (no norm, no activation).
    """

    def __init__(self, channels: tuple[int, int, int], out_dim: int) -> None:
        super().__init__()
        c1, c2, c3 = channels
        self.stem = nn.Sequential(
            nn.Conv2d(3, c1, 7, stride=2, padding=3), nn.InstanceNorm2d(c1), nn.ReLU(inplace=True)
        )
        self.stages = nn.Sequential(
            ResidualBlock(c1, c1),
            ResidualBlock(c1, c1),
            ResidualBlock(c1, c2, stride=2),
            ResidualBlock(c2, c2),
            ResidualBlock(c2, c3),
            ResidualBlock(c3, c3),
        )
        self.head = nn.Conv2d(c3, out_dim, 1)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
                if m.bias is not None:
                    nn.init.zeros_(m.bias)

    def forward(self, image: Tensor) -> Tensor:
        features: Tensor = self.head(self.stages(self.stem(image)))
        return features


def feature_pyramid(features: Tensor) -> list[Tensor]:
    """1/4 features (B,C,h,w) -> [1/16, 1/8, 1/4] maps, the coarser ones average-pooled."""
    return [F.avg_pool2d(features, 4), F.avg_pool2d(features, 2), features]


def split_hidden_context(left_features: Tensor) -> tuple[Tensor, Tensor]:
    """Left features (B,C,h,w) -> GRU hidden state tanh(first half), context ReLU(second half)."""
    hidden, context = torch.chunk(left_features, 2, dim=1)
    return torch.tanh(hidden), torch.relu(context)
