"""full's start from lite's weights: the widened network computes what lite computes."""

from dataclasses import replace
from pathlib import Path

import pytest
import torch

from crestereo_pp.model.config import ModelConfig
from crestereo_pp.model.network import CREStereoPP
from crestereo_pp.model.weights import WEIGHTS_DIR, is_trained, network_from_weights
from crestereo_pp.stereo_data.synthetic import SceneConfig, SceneGenerator
from crestereo_pp.training.widening import copies, fitted_gate, gate_inputs, horizontal_gate, widen, widened_weights
from tests.shared_data import SMALL_STEREO_DEV_PAIR, STEREO_DEV


def test_copies_keep_each_group_and_half_of_lites_channels_together():
    feature = copies(64, 256)  # lite's C to full's: 4 copies in a row
    assert feature[:8] == [0, 0, 0, 0, 1, 1, 1, 1] and feature[-1] == 63
    for channel, source in enumerate(feature):  # correlation groups (4), warp offset groups (8), halves
        assert source is not None
        assert channel // 64 == source // 16 and channel // 32 == source // 8 and channel // 128 == source // 32
    fused = copies(31, 127)  # the motion features but the disparity: 124 copies, 3 new channels
    assert fused[123] == 30 and fused[124:] == [None, None, None]
    with pytest.raises(ValueError, match="cannot widen"):
        copies(64, 32)


def test_the_widened_network_computes_what_lite_computes_where_their_architectures_agree():
    """lite with full's plain 1x5 gate (the one difference widening cannot carry over), its
    weights perturbed so that every part (the zero-initialised offset head too) matters."""
    torch.manual_seed(0)
    lite, full = replace(ModelConfig.preset("lite"), gru_kernels="1x5"), ModelConfig.preset("full")
    small = CREStereoPP(lite).eval()
    with torch.no_grad():
        for parameter in small.parameters():
            parameter.add_(0.05 * torch.randn_like(parameter))
    big = CREStereoPP(full).eval()
    big.load_state_dict(widen(small.state_dict(), lite, full))
    left, right = (255 * torch.rand(1, 3, 64, 128) for _ in range(2))
    with torch.no_grad():
        expected, widened = small(left, right, iters=(2, 2, 2)), big(left, right, iters=(2, 2, 2))
    assert expected.disparity.abs().max() > 1.0  # px: something to compare
    torch.testing.assert_close(widened.disparity, expected.disparity, atol=1e-3, rtol=1e-4)
    torch.testing.assert_close(widened.uncertainty, expected.uncertainty, atol=1e-4, rtol=1e-4)
    noisy = CREStereoPP(full).eval()
    noisy.load_state_dict(widen(small.state_dict(), lite, full, noise=0.01))
    with torch.no_grad():
        differs = (noisy(left, right, iters=(2, 2, 2)).disparity - expected.disparity).abs().max()
    assert 0 < differs < 0.1 * expected.disparity.abs().max()  # copies pulled apart, a little


def test_fulls_gate_is_the_1x5_convolution_that_best_reproduces_lites_super_kernel_on_its_inputs():
    """Fitted on four small procedural scenes, scored on the gate inputs of another scene: the 1x5
    conv reproduces most of the variation of lite's chained 1x15 + 1x5 gate there."""
    from crestereo_pp.model.weights import read_weights

    lite = network_from_weights(read_weights(WEIGHTS_DIR / "lite.pt"), "lite")
    weight, bias = fitted_gate(lite, 5, scenes=4, size=(96, 192))
    gate, first, last = horizontal_gate(lite)
    assert weight.shape == (last.out_channels, first.in_channels, 1, 5) and bias.shape == (weight.shape[0],)
    scene = SceneGenerator(SceneConfig(height=64, width=128, max_disparity=24.0)).generate(1, seed=99)
    x = gate_inputs(lite, scene.left, scene.right)[-1]  # the last (1/4) stage's last gate input
    with torch.no_grad():
        target = gate(x)
        fitted = torch.nn.functional.conv2d(x, weight, bias, padding=(0, 2))
    relative = float((fitted - target).pow(2).mean() / target.var())
    assert relative < 0.2, relative  # measured: 0.10


@pytest.mark.skipif(not STEREO_DEV.is_dir(), reason=f"no real stereo pairs at {STEREO_DEV}")
def test_the_widened_weights_file_records_where_it_comes_from_and_its_validation(tmp_path: Path):
    data = tmp_path / "dev"
    data.mkdir()
    (data / SMALL_STEREO_DEV_PAIR).symlink_to(STEREO_DEV / SMALL_STEREO_DEV_PAIR)
    payload = widened_weights(WEIGHTS_DIR / "lite.pt", noise=0.01, seed=0, val_data=str(data))
    assert payload["model_name"] == "full" and ModelConfig.from_dict(payload["config"]) == ModelConfig.preset("full")
    run = payload["training"]["runs"][-1]
    assert run["origin"].startswith("widened from lite ") and run["pairs"] == 0
    assert payload["training"]["total_pairs"] > 100_000  # lite's training, which these weights carry
    assert run["validation"]["bad2"] < 15.0  # tsukuba in one pass: a network that matches
    assert is_trained(payload["training"])
    network_from_weights(payload, "full")  # loads as full
