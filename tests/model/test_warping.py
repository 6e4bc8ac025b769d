"""Warping: grid_sample deformable sampling against slow direct references (paper eqs. 2, 3)."""

import math

import torch

from crestereo_pp.model.warping import ContentAwareWarp, bilinear_warp, deformable_sample, sampling_grid


def bilinear_at(feature: torch.Tensor, x: float, y: float) -> torch.Tensor:
    """Obviously-correct bilinear read of feature (C, H, W) at (x, y); zeros outside."""
    c, height, width = feature.shape
    x0, y0 = math.floor(x), math.floor(y)
    value = torch.zeros(c, dtype=feature.dtype)
    for yy in (y0, y0 + 1):
        for xx in (x0, x0 + 1):
            weight = (1 - abs(x - xx)) * (1 - abs(y - yy))
            if 0 <= xx < width and 0 <= yy < height and weight > 0:
                value += weight * feature[:, yy, xx]
    return value


def reference_deformable_sample(feature, x, y):
    b, c, _, _ = feature.shape
    groups, points, h, w = x.shape[1:]
    out = torch.zeros(b, c, points, h, w, dtype=feature.dtype)
    per_group = c // groups
    for bi in range(b):
        for g in range(groups):
            channels = slice(g * per_group, (g + 1) * per_group)
            for k in range(points):
                for i in range(h):
                    for j in range(w):
                        out[bi, channels, k, i, j] = bilinear_at(
                            feature[bi, channels], float(x[bi, g, k, i, j]), float(y[bi, g, k, i, j])
                        )
    return out


def test_grid_sample_deformable_sampling_equals_direct_loops_on_random_positions():
    torch.manual_seed(0)
    feature = torch.randn(2, 6, 5, 7, dtype=torch.float64)
    # positions spread over and beyond the map (zeros outside), per group and point
    x = torch.rand(2, 3, 9, 4, 5, dtype=torch.float64) * 10 - 1.5
    y = torch.rand(2, 3, 9, 4, 5, dtype=torch.float64) * 7 - 1.0
    fast = deformable_sample(feature, x, y)
    slow = reference_deformable_sample(feature, x, y)
    assert torch.allclose(fast, slow, atol=1e-5)


def test_content_aware_warp_equals_the_deformable_convolution_of_eq3_computed_directly():
    torch.manual_seed(1)
    c, h, w, groups = 4, 5, 6, 2
    warp = ContentAwareWarp(feature_dim=c, offset_hidden=4, groups=groups, max_offset=10.0)
    right = torch.randn(1, c, h, w)
    disparity = torch.rand(1, 1, h, w) * 3
    offsets = torch.randn(1, groups, 9, h, w)
    fast = warp.deform(right, disparity, offsets)

    slow = torch.zeros(1, c, h, w)
    for i in range(h):
        for j in range(w):
            acc = warp.bias.detach().clone()
            for k in range(9):
                ky, kx = k // 3 - 1, k % 3 - 1
                ni, nj = min(max(i + ky, 0), h - 1), min(max(j + kx, 0), w - 1)  # d(p+k), border replicated
                for g in range(groups):
                    ch = slice(g * c // groups, (g + 1) * c // groups)
                    xs = j + kx - float(disparity[0, 0, ni, nj]) + float(offsets[0, g, k, i, j])
                    sample = bilinear_at(right[0, ch], xs, i + ky)
                    acc += warp.weight.detach()[:, ch, ky + 1, kx + 1] @ sample
            slow[0, :, i, j] = acc
    assert torch.allclose(fast, slow, atol=1e-5)


def test_bilinear_warp_by_integer_disparity_shifts_the_right_map():
    right = torch.arange(2 * 3 * 8, dtype=torch.float32).view(1, 2, 3, 8)
    warped = bilinear_warp(right, torch.full((1, 1, 3, 8), 2.0))
    assert torch.allclose(warped[..., 2:], right[..., :-2], atol=1e-4)  # left x matches right x - 2
    assert warped[..., :2].abs().max() < 1e-4  # matches outside the map read zeros


def identity_weights(c: int, taps: list[int]) -> torch.Tensor:
    weight = torch.zeros(c, c, 9)
    for k in taps:
        weight[:, :, k] = torch.eye(c) / len(taps)
    return weight.view(c, c, 3, 3)


def test_content_aware_warp_with_zero_offsets_and_centre_weight_is_plain_bilinear_warp():
    torch.manual_seed(2)
    warp = ContentAwareWarp(feature_dim=8, offset_hidden=8, groups=8, max_offset=10.0)
    with torch.no_grad():
        warp.weight.copy_(identity_weights(8, [4]))
        warp.bias.zero_()
    right, left = torch.randn(2, 8, 6, 9), torch.randn(2, 8, 6, 9)
    disparity = torch.rand(2, 1, 6, 9) * 4
    # the offset CNN's last layer starts at zero, so the learned offsets are zero here
    out = warp(warp.left_response(left), right, disparity, uncertainty=torch.rand(2, 1, 6, 9))
    assert torch.allclose(out, bilinear_warp(right, disparity), atol=1e-6)


def test_content_aware_warp_with_zero_offsets_and_uniform_weights_is_eq2_mean_of_bilinear_warps():
    torch.manual_seed(3)
    warp = ContentAwareWarp(feature_dim=8, offset_hidden=8, groups=8, max_offset=10.0)
    with torch.no_grad():
        warp.weight.copy_(identity_weights(8, list(range(9))))
        warp.bias.zero_()
    right = torch.randn(1, 8, 7, 10)
    disparity = torch.rand(1, 1, 7, 10) * 4
    out = warp.deform(right, disparity, torch.zeros(1, 8, 9, 7, 10))
    # eq. 2 with c_k = 1/9: mean over k of F_R(p + k - d(p + k)) = 3x3 mean of the plain warp,
    # where neighbours beyond the border use the border disparity at their own position.
    padded_d = torch.nn.functional.pad(disparity, (1, 1, 1, 1), mode="replicate")
    big = torch.nn.functional.pad(right, (1, 1, 1, 1))
    warped_big = bilinear_warp(big, padded_d)  # plain warp evaluated on the 1-pixel larger grid
    expected = torch.nn.functional.avg_pool2d(warped_big, 3, stride=1)
    assert torch.allclose(out, expected, atol=1e-5)


class _Grid(torch.nn.Module):
    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return sampling_grid(x, y)


def test_exported_sampling_grid_has_no_concatenation_and_equals_the_eager_stack():
    x = torch.rand(1, 8, 9, 6, 10) * 2 - 1
    y = torch.rand(1, 8, 9, 6, 10) * 2 - 1
    program = torch.export.export(_Grid(), (x, y))
    targets = {str(node.target) for node in program.graph.nodes if node.op == "call_function"}
    assert not any("cat" in target or "stack" in target for target in targets), targets
    exported = program.module()(x, y)
    assert torch.equal(exported, sampling_grid(x, y))
    assert torch.equal(sampling_grid(x, y)[..., 0], x) and torch.equal(sampling_grid(x, y)[..., 1], y)
