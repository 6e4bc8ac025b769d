"""Training loss, paper eq. 6."""

import pytest
import torch

from model import sequence_loss


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
