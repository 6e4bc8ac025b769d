"""Training loss, paper eq. 6."""

import pytest
import torch

from crestereo_pp.training.loss import matching_loss, sequence_loss


def test_sequence_loss_weights_each_stage_by_gamma_to_the_remaining_iterations():
    gt = torch.tensor([[[[1.0, 2.0, float("inf"), 600.0]]]])
    valid = torch.tensor([[[[True, True, False, True]]]])  # inf invalid; 600 beyond max_disparity
    stage_a = [torch.full((1, 1, 1, 4), 3.0), torch.full((1, 1, 1, 4), 2.0)]
    stage_b = [torch.full((1, 1, 1, 4), 1.0)]
    # stage a: 0.8 * mean(|3-1|, |3-2|) + 1 * mean(|2-1|, |2-2|) = 0.8 * 1.5 + 0.5 ; stage b: mean(0, 1)
    expected = 0.8 * 1.5 + 0.5 + 0.5
    loss = sequence_loss([stage_a, stage_b], gt, valid, gamma=0.8, max_disparity=512.0)
    assert loss.item() == pytest.approx(expected)


def test_sequence_loss_gradient_is_finite_when_ground_truth_holds_inf_and_nan():
    pred = torch.zeros(1, 1, 2, 2, requires_grad=True)
    gt = torch.tensor([[[[1.0, float("inf")], [float("nan"), 2.0]]]])
    loss = sequence_loss([[pred]], gt, torch.isfinite(gt))
    loss.backward()
    assert torch.isfinite(pred.grad).all() and pred.grad[0, 0, 0, 1] == 0


def shifted_views(disparity_px: int, scale: int = 4, channels: int = 64, width: int = 24):
    """Right features at random, left features = right features moved right by disparity/scale:
    F_L(x) = F_R(x - d/scale), so the true match of every left feature pixel is known."""
    torch.manual_seed(0)
    right = torch.randn(1, channels, 3, width)
    shift = disparity_px // scale
    left = torch.nn.functional.pad(right[..., : width - shift], (shift, 0))
    gt = torch.full((1, 1, 3 * scale, width * scale), float(disparity_px))
    return left, right, gt, torch.ones_like(gt, dtype=torch.bool)


def test_matching_loss_is_lowest_when_features_peak_at_the_true_disparity():
    left, right, gt, valid = shifted_views(disparity_px=8)
    sharp = matching_loss(2 * left, 2 * right, gt, valid, max_disparity=32.0)
    wrong = matching_loss(2 * left, 2 * right, gt + 8.0, valid, max_disparity=32.0)
    assert sharp.item() < 0.05 < wrong.item()


def test_matching_loss_ignores_blocks_across_depth_edges_invalid_and_out_of_range_pixels():
    left, right, gt, valid = shifted_views(disparity_px=8)
    edge_block = torch.zeros_like(valid)
    edge_block[..., :4, 40:44] = True  # feature pixel (0, 10)
    edged, far = gt.clone(), gt.clone()
    edged[..., :4, 40:42] = 30.0  # half of the block at 30 px, half at 8: no single true match
    far[..., :4, 40:44] = 40.0  # beyond max_disparity
    without_block = matching_loss(left, right, gt, valid & ~edge_block, 32.0)
    assert without_block.item() != pytest.approx(matching_loss(left, right, gt, valid, 32.0).item(), rel=1e-3)
    for variant in (edged, far):
        assert matching_loss(left, right, variant, valid, 32.0).item() == pytest.approx(without_block.item(), rel=1e-5)


def test_matching_loss_gradient_is_finite_and_reaches_both_views():
    left, right, gt, valid = shifted_views(disparity_px=12)
    left.requires_grad_(True)
    right.requires_grad_(True)
    gt[..., 0, 0] = float("inf")
    matching_loss(left, right, gt, valid & torch.isfinite(gt), 32.0).backward()
    assert torch.isfinite(left.grad).all() and torch.isfinite(right.grad).all()
    assert left.grad.abs().sum() > 0 and right.grad.abs().sum() > 0
