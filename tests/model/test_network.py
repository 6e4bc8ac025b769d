"""The network as a whole: size, training signal, ablation switches."""

import dataclasses

import pytest
import torch

from crestereo_pp.model import CREStereoPP, ModelConfig
from crestereo_pp.training.loss import sequence_loss


def count(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


@pytest.mark.parametrize(("name", "low", "high"), [("lite", 0.58e6, 0.68e6), ("full", 4.5e6, 7.5e6)])
def test_parameter_count_is_in_the_papers_range(name, low, high):
    net = CREStereoPP(ModelConfig.preset(name))
    breakdown = {
        "FEM": count(net.fem),
        "deformable warp (UGAC)": count(net.ugac),
        "update block (ARM)": count(net.update),
    }
    print(f"\n{name}: {count(net):,} parameters")
    for part, n in breakdown.items():
        print(f"  {part:<24} {n:>10,}")
    assert sum(breakdown.values()) == count(net)
    assert low <= count(net) <= high


def test_lite_blocks_match_the_authors_lite_code_up_to_the_one_channel_disparity():
    # Authors' Lite code: FEM 273,952 exactly; its deformable module (104,456) and update block
    # (253,216) carry a 2-channel flow whose y part is always zero, ours a 1-channel disparity.
    net = CREStereoPP(ModelConfig.preset("lite"))
    assert count(net.fem) == 273_952
    assert 104_456 - count(net.ugac) == 288  # offset CNN input 129 instead of 130 channels
    assert 253_216 - count(net.update) == 1_712  # disparity encoder, fuse and head: 1 channel less


def synthetic_pair(height=64, width=96, disparity=5.0, seed=0):
    """A textured right image and the left image that sees it shifted by a constant disparity."""
    g = torch.Generator().manual_seed(seed)
    right = torch.rand(1, 3, height, width + 16, generator=g) * 255
    right = torch.nn.functional.avg_pool2d(right, 3, stride=1, padding=1)
    shift = int(disparity)
    left = right[..., :width]
    right = right[..., shift : width + shift]  # left(x) = right(x - d)  <=>  right(x) = left(x + d)
    gt = torch.full((1, 1, height, width), disparity)
    return left.contiguous(), right.contiguous(), gt


def overfit(net: CREStereoPP, optimiser: torch.optim.Optimizer, steps: int) -> list[float]:
    """Train ``net`` on one synthetic pair for ``steps`` steps; the loss of each step."""
    left, right, gt = synthetic_pair()
    valid = torch.ones_like(gt, dtype=torch.bool)
    losses = []
    for _ in range(steps):
        optimiser.zero_grad()
        loss = sequence_loss(net(left, right).predictions, gt, valid)
        loss.backward()
        optimiser.step()
        losses.append(loss.item())
    return losses


def test_gradients_reach_every_parameter_through_the_loss():
    torch.manual_seed(0)
    net = CREStereoPP(ModelConfig.preset("lite")).train()
    # two steps: the offset CNN's last layer starts at zero and blocks gradients upstream of it
    overfit(net, torch.optim.SGD(net.parameters(), lr=1e-3), steps=2)
    silent = [n for n, p in net.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert silent == []


def test_loss_decreases_when_overfitting_one_synthetic_pair():
    torch.manual_seed(0)
    net = CREStereoPP(ModelConfig.preset("lite")).train()
    losses = overfit(net, torch.optim.Adam(net.parameters(), lr=4e-4), steps=30)
    print(f"\nloss: first {losses[0]:.3f}, last {losses[-1]:.3f}")
    assert sum(losses[-5:]) / 5 < 0.5 * sum(losses[:5]) / 5


def test_training_mode_returns_every_prediction_of_every_stage_at_full_resolution():
    net = CREStereoPP(ModelConfig.preset("lite")).train()
    left, right, _ = synthetic_pair()
    out = net(left, right)
    assert [len(stage) for stage in out.predictions] == [2, 4, 6]
    assert all(p.shape == (1, 1, 64, 96) for stage in out.predictions for p in stage)
    assert out.disparity is out.predictions[-1][-1]


ABLATIONS = [
    {"warping": "bilinear"},
    {"warping": "content_aware"},
    {"uncertainty": "variance_tanh"},
    {"uncertainty": "error_aware"},
    {"gru_kernels": "3x3"},
    {"gru_kernels": "1x5"},
    {"gru_kernels": "1x15"},
    {"gru_kernels": "1x5+1x15+1x31"},
]


@pytest.mark.parametrize("switch", ABLATIONS, ids=lambda s: "-".join(f"{k}={v}" for k, v in s.items()))
def test_every_ablation_switch_builds_and_runs(switch):
    config = ModelConfig.preset("lite", **switch, iters=(1, 1, 2))
    net = CREStereoPP(config).eval()
    left, right, _ = synthetic_pair(32, 64)
    with torch.inference_mode():
        out = net(left, right)
    assert out.disparity.shape == (1, 1, 32, 64) and torch.isfinite(out.disparity).all()
    assert ((out.uncertainty >= 0) & (out.uncertainty <= 1)).all()


def test_gru_kernel_ablation_parameter_counts_follow_the_papers_order():
    counts = {
        k: count(CREStereoPP(ModelConfig.preset("lite", gru_kernels=k)))
        for k in ("3x3", "1x5", "1x15", "1x5+1x15", "1x5+1x15+1x31")
    }
    assert counts["3x3"] < counts["1x5"] < counts["1x15"] < counts["1x5+1x15"] < counts["1x5+1x15+1x31"]
    bilinear = count(CREStereoPP(ModelConfig.preset("lite", warping="bilinear")))
    assert bilinear < counts["1x5+1x15"]


def test_config_round_trips_through_a_plain_dict_and_rejects_bad_values():
    config = ModelConfig.preset("full", warping="content_aware")
    assert ModelConfig.from_dict(config.to_dict()) == config
    with pytest.raises(ValueError, match="unknown model preset"):
        ModelConfig.preset("huge")
    with pytest.raises(ValueError, match="iters"):
        dataclasses.replace(config, iters=(1, 0, 2))


def test_input_that_is_not_a_multiple_of_32_is_refused_by_the_bare_network():
    net = CREStereoPP(ModelConfig.preset("lite")).eval()
    with pytest.raises(ValueError, match="multiple of 32"):
        net(torch.zeros(1, 3, 40, 64), torch.zeros(1, 3, 40, 64))


def test_wide_horizontal_convs_equal_the_plain_convolution():
    from crestereo_pp.model.convolution import WideHorizontalConv

    torch.manual_seed(0)
    conv = WideHorizontalConv(12, 8, (1, 15), padding=(0, 7), groups=2)
    x = torch.randn(2, 12, 5, 40)
    plain = torch.nn.functional.conv2d(x, conv.weight, conv.bias, padding=(0, 7), groups=2)
    assert conv.weight.shape == (8, 6, 1, 15)  # state dicts are those of nn.Conv2d
    torch.testing.assert_close(conv(x), plain, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("kernels", ["3x3", "1x5+1x15"])
def test_the_gru_with_the_context_convolved_once_per_stage_equals_the_gru_on_the_whole_input(kernels):
    from crestereo_pp.model.update import ConvGRU, SeparableConvGRU

    torch.manual_seed(1)
    hidden = 6
    gru = ConvGRU(hidden, 2 * hidden) if kernels == "3x3" else SeparableConvGRU(hidden, 2 * hidden, kernels)
    h, motion, context = (torch.randn(2, hidden, 5, 20, dtype=torch.float64) for _ in range(3))
    gru = gru.double()

    def step(h, zr, q):  # the textbook ConvGRU on x = [motion, context]
        x = torch.cat((motion, context), dim=1)
        z, r = torch.sigmoid(zr(torch.cat((h, x), dim=1))).chunk(2, dim=1)
        return (1 - z) * h + z * torch.tanh(q(torch.cat((r * h, x), dim=1)))

    if kernels == "3x3":
        expected = step(h, gru.zr, gru.q)
    else:
        expected = step(step(h, gru.zr1, gru.q1), gru.zr2, gru.q2)
    terms = gru.context_terms(context)
    torch.testing.assert_close(gru(h, motion, terms), expected)
    torch.testing.assert_close(gru(h, motion, terms), gru(h, motion, terms))  # the terms are reusable


def test_the_offset_cnn_with_the_left_features_convolved_once_equals_it_on_the_whole_input():
    from crestereo_pp.model.warping import OffsetNet

    torch.manual_seed(2)
    net = OffsetNet(feature_dim=8, hidden=12, groups=4, max_offset=10.0).double()
    torch.nn.init.normal_(net.layers[-1].weight)  # zero-initialised: make the offsets non-zero
    left, warped = torch.randn(2, 2, 8, 6, 11, dtype=torch.float64)
    disparity = torch.rand(2, 1, 6, 11, dtype=torch.float64) * 5
    expected = 10.0 * torch.tanh(net.layers(torch.cat((left, warped, disparity), dim=1))).view(2, 4, 9, 6, 11)
    assert expected.abs().max() > 1.0
    torch.testing.assert_close(net(net.left_response(left), warped, disparity), expected)
