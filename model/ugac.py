"""Uncertainty guided adaptive correlation (UGAC, paper sec. 3.2): warp, correlate, estimate U."""

from __future__ import annotations

from torch import Tensor, nn

from .config import ModelConfig
from .correlation import group_correlation, window_for_iteration
from .uncertainty import estimate_uncertainty
from .warping import ContentAwareWarp, bilinear_warp


class UGAC(nn.Module):
    """One UGAC step: (F_L, F_R, d_{n-1}, U_{n-1}) -> (V_n, U_n).

    ``config.warping`` picks the ablation: ``bilinear`` (no learned warp), ``content_aware``
    (deformable warp, offsets not scaled), ``ugac`` (offsets scaled by U_{n-1}).
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        self.warp = (
            None
            if config.warping == "bilinear"
            else ContentAwareWarp(config.feature_dim, config.offset_hidden, config.offset_groups, config.max_offset)
        )

    def left_response(self, left: Tensor) -> Tensor | None:
        """What the warp needs from the left features (B, C, h, w) of a scale, computed once per
        stage (their share of the offset CNN's first convolution); None without a learned warp."""
        return None if self.warp is None else self.warp.left_response(left)

    def forward(
        self,
        left: Tensor,
        left_response: Tensor | None,
        right: Tensor,
        disparity: Tensor,
        uncertainty: Tensor | None,
        iteration: int,
    ) -> tuple[Tensor, Tensor]:
        """
        Args:
            left, right: (B, C, h, w) features of one scale; left_response: ``left_response(left)``.
            disparity: (B, 1, h, w) current disparity d_{n-1}, positive, pixels of this scale.
            uncertainty: (B, 1, h, w) U_{n-1} in [0, 1], or None at a stage's first iteration (U = 1).
            iteration: n within the stage; picks the correlation window (1x9 / 3x3 alternate).
        Returns:
            V_n (B, groups * 9, h, w) and U_n (B, 1, h, w).
        """
        if self.warp is None:
            warped = bilinear_warp(right, disparity)
        else:
            assert left_response is not None, "a learned warp needs left_response(left)"
            scale = uncertainty if self.config.warping == "ugac" else None
            warped = self.warp(left_response, right, disparity, scale)
        volume = group_correlation(left, warped, self.config.corr_groups, window_for_iteration(iteration))
        return volume, estimate_uncertainty(self.config.uncertainty, volume, left, warped)
