"""Group-wise local correlation (eq. 1) and variance-based uncertainty (eq. 4)."""

import pytest
import torch

from crestereo_pp.model.correlation import group_correlation, window_for_iteration
from crestereo_pp.model.uncertainty import estimate_uncertainty


def test_correlation_window_alternates_line_and_square_starting_with_the_line():
    assert [window_for_iteration(n) for n in range(4)] == ["1x9", "3x3", "1x9", "3x3"]


@pytest.mark.parametrize("window", ["1x9", "3x3"])
def test_group_correlation_is_the_group_mean_of_channel_products_at_each_candidate(window):
    torch.manual_seed(0)
    left, right = torch.randn(2, 8, 5, 11), torch.randn(2, 8, 5, 11)
    volume = group_correlation(left, right, groups=4, window=window)
    assert volume.shape == (2, 36, 5, 11)
    shifts = (
        [(0, dx) for dx in range(-4, 5)] if window == "1x9" else [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
    )
    for b, i, j in [(0, 2, 5), (1, 0, 0), (1, 4, 10), (0, 3, 2)]:
        for g in range(4):
            for r, (dy, dx) in enumerate(shifts):
                y, x = i + dy, j + dx
                inside = 0 <= y < 5 and 0 <= x < 11
                expected = (
                    (left[b, 2 * g : 2 * g + 2, i, j] * right[b, 2 * g : 2 * g + 2, y, x]).mean() if inside else 0.0
                )
                assert volume[b, 9 * g + r, i, j].item() == pytest.approx(float(expected), abs=1e-6)


@pytest.mark.parametrize("window", ["1x9", "3x3"])
def test_an_exported_graph_computes_the_same_volume_with_one_mean_over_the_stacked_candidates(window):
    class Volume(torch.nn.Module):
        def forward(self, left, right):
            return group_correlation(left, right, groups=4, window=window)

    torch.manual_seed(2)
    left, right = torch.randn(2, 8, 5, 11), torch.randn(2, 8, 5, 11)
    program = torch.export.export(Volume(), (left, right))
    means = [node for node in program.graph.nodes if node.target == torch.ops.aten.mean.dim]
    assert len(means) == 1  # eager torch takes one mean per candidate, nine
    torch.testing.assert_close(program.module()(left, right), group_correlation(left, right, 4, window))


def test_correlation_peaks_at_the_true_residual_shift():
    torch.manual_seed(1)
    left = torch.randn(1, 128, 4, 20)
    right = torch.roll(left, shifts=3, dims=-1)  # left(x) == right(x + 3)
    volume = group_correlation(left, right, groups=4, window="1x9").view(1, 4, 9, 4, 20)
    assert (volume[..., 4:12].argmax(dim=2) == 4 + 3).all()


def test_flat_cost_volume_gives_uncertainty_exactly_one_half():
    volume = torch.full((2, 36, 3, 4), 0.7)
    u = estimate_uncertainty("variance_sigmoid", volume, torch.zeros(2, 8, 3, 4), torch.zeros(2, 8, 3, 4))
    assert torch.equal(u, torch.full((2, 1, 3, 4), 0.5))


def test_peaked_cost_volume_gives_uncertainty_near_zero():
    volume = torch.zeros(1, 36, 2, 2)
    volume[:, 4] = 40.0  # one candidate far above the rest
    u = estimate_uncertainty("variance_sigmoid", volume, torch.zeros(1, 8, 2, 2), torch.zeros(1, 8, 2, 2))
    assert u.max() < 1e-6


def test_uncertainty_falls_as_the_volume_gets_more_peaked():
    volume = torch.zeros(1, 36, 1, 3)
    volume[0, 0, 0] = torch.tensor([0.5, 2.0, 8.0])
    u = estimate_uncertainty("variance_sigmoid", volume, torch.zeros(1, 8, 1, 3), torch.zeros(1, 8, 1, 3))
    assert u[0, 0, 0, 0] > u[0, 0, 0, 1] > u[0, 0, 0, 2]


def test_ablation_uncertainties_stay_in_unit_range_with_their_documented_fixed_points():
    torch.manual_seed(2)
    volume, left, warped = torch.randn(1, 36, 4, 4) * 3, torch.randn(1, 8, 4, 4), torch.randn(1, 8, 4, 4)
    for mode in ("variance_sigmoid", "variance_tanh", "error_aware"):
        u = estimate_uncertainty(mode, volume, left, warped)
        assert u.shape == (1, 1, 4, 4) and (u >= 0).all() and (u <= 1).all()
    flat = torch.zeros(1, 36, 2, 2)
    assert torch.equal(estimate_uncertainty("variance_tanh", flat, left, warped)[..., :2, :2], torch.ones(1, 1, 2, 2))
    same = torch.randn(1, 8, 2, 2)
    assert torch.equal(estimate_uncertainty("error_aware", flat, same, same), torch.zeros(1, 1, 2, 2))
