"""CREStereo++: FEM + one adaptive recurrent module (ARM) run coarse to fine (paper sec. 3.1)."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from .config import ModelConfig
from .feature_extractor import FeatureExtractor, feature_pyramid, split_hidden_context
from .ugac import UGAC
from .update import UpdateBlock
from .upsample import convex_upsample, resize_disparity

SCALES = (16, 8, 4)
"""Downsampling factor of each ARM stage, coarse to fine."""

INPUT_MULTIPLE = 32
"""Input height and width must be multiples of this (``inference.padding`` pads to it)."""


def padded_size(size: int) -> int:
    """``size`` (an input height or width, px) rounded up to a multiple of INPUT_MULTIPLE."""
    return -(-size // INPUT_MULTIPLE) * INPUT_MULTIPLE


def finest_stage_only(iters: tuple[int, int, int]) -> tuple[int, int, int]:
    """``iters`` (at 1/16, 1/8, 1/4) with the coarse stages skipped: what refining a given
    disparity at 1/4 only runs (the second of two passes)."""
    return (0, 0, iters[-1])


@dataclass
class NetworkOutput:
    """What one forward pass returns. Disparities are positive, in pixels of the input.

    Attributes:
        disparity: (B, 1, H, W) final prediction.
        uncertainty: (B, 1, H, W) U of the last iteration in [0, 1], bilinearly upsampled.
        predictions: per stage, per iteration, (B, 1, H, W) full-resolution disparities for the
            loss (paper eq. 6); empty unless the network is in training mode.
        features: (left, right) FEM features (B, C, H/4, W/4) for training-only losses
            (``training.loss.matching_loss``); None unless the network is in training mode.
    """

    disparity: Tensor
    uncertainty: Tensor
    predictions: list[list[Tensor]] = field(default_factory=list)
    features: tuple[Tensor, Tensor] | None = None


class CREStereoPP(nn.Module):
    """CREStereo++ / Lite-CREStereo++ depending on ``config``.

    One FEM shared by both views (run as one batch); one ARM (UGAC + update block) whose SAME
    parameters serve 1/16, 1/8 and 1/4. The last disparity of a stage, upsampled x2 and scaled
    x2, initialises the next; the final 1/4 disparity is convex-upsampled to full resolution.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        self.fem = FeatureExtractor(config.fem_channels, config.feature_dim)
        self.ugac = UGAC(config)
        self.update = UpdateBlock(config)

    def forward(
        self,
        left: Tensor,
        right: Tensor,
        iters: tuple[int, int, int] | None = None,
        init_disparity: Tensor | None = None,
    ) -> NetworkOutput:
        """
        Args:
            left, right: (B, 3, H, W) RGB in [0, 255]; H and W multiples of 32.
            iters: iterations at 1/16, 1/8, 1/4 (default ``config.iters``); a stage with 0 is
                skipped (``finest_stage_only``), the 1/4 one must run.
            init_disparity: optional (B, 1, H, W) start, positive, in pixels of the input: the
                first stage that runs starts from it (averaged down to that stage's resolution)
                instead of from zero. A video's warm start runs every stage from it, the second
                of two passes 1/4 only (``inference.warm_start.WarmStart`` says why).
        """
        height, width = left.shape[-2:]
        if height % INPUT_MULTIPLE or width % INPUT_MULTIPLE:
            raise ValueError(f"input {height}x{width} is not a multiple of {INPUT_MULTIPLE}; pad it first")
        iters = iters or self.config.iters
        images = torch.cat((left, right), dim=0) * (2.0 / 255.0) - 1.0
        features = self.fem(images)
        batch = left.shape[0]  # sliced, not chunked: an export keeps the batch size symbolic
        left_features, right_features = features[:batch], features[batch:]
        pyramid = list(zip(feature_pyramid(left_features), feature_pyramid(right_features), strict=True))

        if iters[-1] < 1:
            raise ValueError(f"the 1/4 stage must run at least one iteration, got {iters}")
        first_stage = next(stage for stage, count in enumerate(iters) if count > 0)
        if init_disparity is None:
            f_left = pyramid[first_stage][0]
            # float32 even under bf16 autocast: the disparity accumulates over every iteration
            disparity = f_left.new_zeros(f_left.shape[0], 1, *f_left.shape[-2:], dtype=torch.float32)
        else:
            disparity = F.avg_pool2d(init_disparity, SCALES[first_stage]) / SCALES[first_stage]

        predictions: list[list[Tensor]] = []
        for stage in range(first_stage, len(SCALES)):
            if stage > first_stage:
                disparity = resize_disparity(disparity, *pyramid[stage][0].shape[-2:])
            f_left, f_right = pyramid[stage]
            hidden, context = split_hidden_context(f_left)
            # what the left features and the context contribute is the same at every iteration
            left_response = self.ugac.left_response(f_left)
            context_terms = self.update.context_terms(context)
            uncertainty: Tensor | None = None  # U = 1 at the start of every stage
            stage_predictions: list[Tensor] = []
            for n in range(iters[stage]):
                disparity = disparity.detach()
                volume, next_uncertainty = self.ugac(f_left, left_response, f_right, disparity, uncertainty, n)
                hidden, delta = self.update(hidden, context_terms, volume, disparity)
                disparity = disparity + delta.float()
                uncertainty = next_uncertainty
                if self.training:
                    stage_predictions.append(self.full_resolution(disparity, hidden, height, width))
            predictions.append(stage_predictions)

        assert uncertainty is not None  # the 1/4 stage runs at least one iteration
        final = predictions[-1][-1] if self.training else self.full_resolution(disparity, hidden, height, width)
        full_uncertainty = F.interpolate(uncertainty, size=(height, width), mode="bilinear", align_corners=False)
        if not self.training:
            return NetworkOutput(final, full_uncertainty)
        return NetworkOutput(final, full_uncertainty, predictions, (left_features, right_features))

    def full_resolution(self, disparity: Tensor, hidden: Tensor, height: int, width: int) -> Tensor:
        """Convex-upsample a stage's disparity x4, then (coarse stages) resize bilinearly to H x W."""
        fine = convex_upsample(disparity, self.update.upsample_mask(hidden))
        if fine.shape[-1] == width:
            return fine
        return resize_disparity(fine, height, width)
