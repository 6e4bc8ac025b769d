"""Spec of stereo_data.synthetic: exact, deterministic procedural stereo pairs."""

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from crestereo_pp.stereo_data.photos import PHOTOS, load_photos
from crestereo_pp.stereo_data.synthetic import MAX_SIDES, PhotometricConfig, Scene, SceneConfig, SceneGenerator
from crestereo_pp.stereo_data.synthetic.draw import Draw
from crestereo_pp.stereo_data.synthetic.geometry import covers, seen_from_right, surface_disparity
from crestereo_pp.stereo_data.synthetic.hard_cases import SurfaceKinds, repetitive_period_texels
from crestereo_pp.stereo_data.synthetic.visibility import nearest_surface, view_bounds


@pytest.fixture(autouse=True, scope="module")
def one_cpu_thread():
    """These tensors are tiny: on a small shared CPU, thread start-up and contention cost more
    than the work, so run this module single-threaded (and restore the setting after)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


SMALL = SceneConfig(height=64, width=128, surfaces=12, min_surfaces=6, texture_size=64)
CLEAN = replace(SMALL, photometric=None)


def warp_right_to_left(right: torch.Tensor, disparity: torch.Tensor) -> torch.Tensor:
    """Bilinearly sample right (B, C, H, W) at (x - d, y) for every left pixel."""
    batch, _, height, width = right.shape
    x = torch.arange(width, dtype=torch.float32).view(1, 1, -1) - disparity[:, 0]
    y = torch.arange(height, dtype=torch.float32).view(1, -1, 1).expand_as(x)
    grid = torch.stack([2 * x / (width - 1) - 1, 2 * y / (height - 1) - 1], dim=-1)
    return F.grid_sample(right, grid, mode="bilinear", align_corners=True)


def test_batch_has_the_contract_shapes_types_and_ranges() -> None:
    batch = SceneGenerator(SMALL).generate(batch_size=3, seed=0)
    for image in (batch.left, batch.right):
        assert image.shape == (3, 3, 64, 128) and image.dtype == torch.float32
        assert image.min() >= 0 and image.max() <= 255
    for mask in (batch.valid, batch.occluded):
        assert mask.shape == (3, 1, 64, 128) and mask.dtype == torch.bool
    assert batch.disparity.shape == (3, 1, 64, 128) and batch.disparity.dtype == torch.float32
    assert batch.valid.all()


def test_default_max_disparity_is_192_at_512_px_and_scales_with_width() -> None:
    assert SceneConfig(width=512).max_disparity == 192
    assert SceneConfig(width=1024).max_disparity == 384
    assert SceneConfig(width=512, max_disparity=64).max_disparity == 64


@pytest.mark.parametrize(
    "bad",
    [
        {"max_slope": 1.0},  # the right view needs 1 - a > 0
        {"min_surfaces": 30},
        {"log2_scale": (-1.0, 0.0)},  # texels would be smaller than a pixel: aliasing
        {"max_disparity": 0.0},
        {"supersample": 0},
        {"texel_size": (0.6, 2.0)},  # under a pixel: needs supersample 2
        {"road_probability": 1.5},
        {"room_probability": -0.5},
        {"curve_probability": -0.1},
        {"lighting_probability": 2.0},
        {"specular_probability": -1.0},
        {"thin_probability": 1.5},
        {"flat_probability": -0.1},
        {"repetitive_probability": 2.0},
        {"wide_range_probability": -1.0},
        {"reflective_probability": 1.5},
        {"row_offset_probability": -0.5},
        {"row_offset": -1.0},
        {"row_offset": 9.0},  # rows that far off are a failed rectification, not a residual
        {"max_disparity": 100.0, "wide_max_disparity": 90.0, "wide_range_probability": 0.5},  # narrower
    ],
)
def test_config_rejects_settings_the_generator_cannot_honour(bad: dict) -> None:
    with pytest.raises(ValueError):
        SceneConfig(**bad)


def test_supersampling_allows_texels_down_to_one_sample() -> None:
    assert SceneConfig(texel_size=(0.6, 2.0), supersample=2).supersample == 2
    with pytest.raises(ValueError):
        SceneConfig(texel_size=(0.4, 2.0), supersample=2)


@pytest.mark.parametrize("layout", [{}, {"thin_probability": 0.5}])
def test_anti_aliased_scenes_keep_the_point_ground_truth_and_blend_only_edge_pixels(layout: dict) -> None:
    point = SceneGenerator(replace(CLEAN, height=96, width=192, **layout))
    smooth = SceneGenerator(replace(CLEAN, height=96, width=192, supersample=2, **layout))
    scene = point.sample_scene(batch_size=2, seed=4)
    scene.contrast.zero_()  # every surface one flat colour: a pixel shows one surface or blends several
    scene.ramp.zero_()
    sharp, blended = point.render(scene), smooth.render(scene)
    assert torch.equal(sharp.disparity, blended.disparity) and torch.equal(sharp.occluded, blended.occluded)

    colors = scene.base.clamp(0, 255)  # (B, S, 3)
    for batch, image in ((sharp, sharp.left), (blended, blended.left)):
        distance = (image[:, None] - colors[..., None, None]).abs().amax(dim=2)  # (B, S, H, W)
        pure = distance.amin(dim=1) < 1e-3
        if batch is sharp:
            assert pure.all()  # point samples: every pixel is exactly one surface's colour
            continue
        disparity = batch.disparity[:, 0]
        span = F.max_pool2d(disparity, 3, 1, 1) + F.max_pool2d(-disparity, 3, 1, 1)  # max - min nearby
        mixed = ~pure
        assert mixed.float().mean() > 0.01  # edges are anti-aliased...
        assert (span[mixed] > 1e-3).float().mean() > 0.95  # ...and only edges blend


@pytest.mark.parametrize("curve_probability", [0.0, 1.0])
@pytest.mark.parametrize("max_disparity", [None, 12.0])
def test_disparity_stays_within_zero_and_max_disparity(max_disparity: float | None, curve_probability: float) -> None:
    config = replace(SMALL, max_disparity=max_disparity, curve_probability=curve_probability)
    batch = SceneGenerator(config).generate(batch_size=8, seed=1)
    assert batch.disparity.min() >= 0
    assert batch.disparity.max() <= config.max_disparity
    assert batch.disparity.max() > 0.5 * config.max_disparity  # and the range is used


def test_same_seed_reproduces_the_batch_bit_for_bit() -> None:
    generator = SceneGenerator(SMALL)
    first, second = generator.generate(batch_size=2, seed=7), generator.generate(batch_size=2, seed=7)
    for name in ("left", "right", "disparity", "valid", "occluded"):
        assert torch.equal(getattr(first, name), getattr(second, name)), name
    assert torch.equal(SceneGenerator(SMALL).generate(batch_size=2, seed=7).left, first.left)


@pytest.mark.parametrize("seed", [-1, 2**32, 2**41])
def test_seeds_beyond_32_bits_are_refused_rather_than_repeating_a_smaller_seeds_scenes(seed: int) -> None:
    """torch's CPU generator keeps a seed's low 32 bits: 2**41 would draw what 0 draws."""
    generator = SceneGenerator(SMALL)
    with pytest.raises(ValueError, match="seeds are in"):
        generator.generate(batch_size=1, seed=seed)
    with pytest.raises(ValueError, match="seeds are in"):
        generator.sample_scene(batch_size=1, seed=seed)


def test_different_seeds_give_different_scenes() -> None:
    generator = SceneGenerator(SMALL)
    first, second = generator.generate(batch_size=2, seed=7), generator.generate(batch_size=2, seed=8)
    assert not torch.equal(first.disparity, second.disparity)
    assert (first.left - second.left).abs().mean() > 10


@pytest.mark.parametrize(
    "layout",
    [
        {},
        {"road_probability": 1.0},
        {"room_probability": 1.0},
        {"curve_probability": 1.0},
        {"lighting_probability": 1.0, "curve_probability": 0.5},
        {"thin_probability": 0.5},
        {"wide_range_probability": 1.0},
        {"flat_probability": 0.3},
        {"repetitive_probability": 0.5},
    ],
)
def test_right_view_warped_by_ground_truth_reproduces_left_where_not_occluded(layout: dict) -> None:
    config = replace(CLEAN, height=96, width=192, **layout)
    batch = SceneGenerator(config).generate(batch_size=4, seed=3)
    visible = (~batch.occluded).expand_as(batch.left)
    error = (warp_right_to_left(batch.right, batch.disparity) - batch.left).abs()[visible]
    zero_disparity_error = (batch.right - batch.left).abs()[visible]
    assert visible.float().mean() > 0.4
    # Exact up to the bilinear interpolation of fine textures and of edges in the right view.
    assert error.median() < 0.5
    assert error.mean() < 2.5
    assert zero_disparity_error.mean() > 15 * error.mean()


@pytest.mark.parametrize("layout", [{}, {"thin_probability": 0.5}, {"wide_range_probability": 1.0}])
def test_warp_is_exact_when_every_surface_is_at_an_integer_fronto_parallel_disparity(layout: dict) -> None:
    generator = SceneGenerator(replace(CLEAN, height=96, width=192, **layout))
    scene = generator.sample_scene(batch_size=4, seed=3)
    scene.plane[..., :2] = 0.0
    scene.plane[..., 2] = scene.plane[..., 2].round()
    batch = generator.render(scene)
    visible = (~batch.occluded).expand_as(batch.left)
    error = (warp_right_to_left(batch.right, batch.disparity) - batch.left).abs()
    assert error[visible].max() < 0.01  # grey levels: only grid_sample coordinate rounding
    assert error[~visible].mean() > 5  # occluded pixels see another surface, or nothing


def test_sample_scene_and_render_give_the_clean_batch() -> None:
    generator = SceneGenerator(CLEAN)
    rendered = generator.render(generator.sample_scene(batch_size=2, seed=5))
    generated = generator.generate(batch_size=2, seed=5)
    assert torch.equal(rendered.left, generated.left) and torch.equal(rendered.right, generated.right)


def test_photometric_changes_touch_only_the_images_and_differ_between_views() -> None:
    clean = SceneGenerator(CLEAN).generate(batch_size=4, seed=11)
    changed = SceneGenerator(SMALL).generate(batch_size=4, seed=11)
    assert torch.equal(clean.disparity, changed.disparity)
    assert torch.equal(clean.occluded, changed.occluded)
    left_change = (changed.left - clean.left).abs().mean(dim=(1, 2, 3))
    right_change = (changed.right - clean.right).abs().mean(dim=(1, 2, 3))
    assert (left_change > 0.5).all() and (right_change > 0.5).all()
    # Asymmetric: the per-channel brightness ratio augmented / clean differs between the views.
    ratio_left = changed.left.mean(dim=(2, 3)) / clean.left.mean(dim=(2, 3))
    ratio_right = changed.right.mean(dim=(2, 3)) / clean.right.mean(dim=(2, 3))
    assert ((ratio_left - ratio_right).abs().amax(dim=1) > 0.02).all()


def test_slanted_surfaces_appear_and_fronto_parallel_scenes_have_none() -> None:
    def smooth_gradients(config: SceneConfig) -> torch.Tensor:
        """|d disparity / dx| between horizontal neighbours on the same surface (not at edges)."""
        disparity = SceneGenerator(config).generate(batch_size=4, seed=2).disparity
        step = (disparity[..., 1:] - disparity[..., :-1]).abs()
        return step[step < 0.9]

    slanted = smooth_gradients(CLEAN)
    assert (slanted > 0.01).float().mean() > 0.2
    fronto_parallel = smooth_gradients(replace(CLEAN, slant_probability=0.0))
    assert (fronto_parallel > 1e-3).float().mean() < 0.002


def smooth_derivatives(disparity: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Central first and second differences of disparity (B, 1, H, W) along x and y, px per px, at
    pixels whose three-pixel windows lie on one smooth surface (|second difference| < 0.05 px: an
    edge between surfaces breaks that unless their disparities nearly meet)."""
    firsts, seconds = [], []
    for dim in (-1, -2):
        before, centre, after = (disparity.narrow(dim, start, disparity.shape[dim] - 2) for start in range(3))
        first, second = (after - before) / 2, after - 2 * centre + before
        smooth = second.abs() < 0.05
        firsts.append(first[smooth])
        seconds.append(second[smooth])
    return torch.cat(firsts), torch.cat(seconds)


def test_curved_surfaces_bend_and_keep_the_slope_bound() -> None:
    config = replace(CLEAN, height=96, width=192, curve_probability=1.0)
    first, second = smooth_derivatives(SceneGenerator(config).generate(batch_size=4, seed=6).disparity)
    assert first.abs().max() <= config.max_slope + 0.03
    assert (second.abs() > 2e-3).float().mean() > 0.05  # bent over a good part of the frame (the background is planar)
    planar = SceneGenerator(replace(config, curve_probability=0.0)).generate(batch_size=4, seed=6)
    _, planar_second = smooth_derivatives(planar.disparity)
    assert (planar_second.abs() > 2e-3).float().mean() < 0.01


def test_curved_scenes_mix_domes_bowls_and_saddles_and_keep_the_background_planar() -> None:
    scene = SceneGenerator(replace(CLEAN, surfaces=24, curve_probability=0.5)).sample_scene(batch_size=8, seed=4)
    assert (scene.curvature[:, 0] == 0).all()
    kxx, kxy, kyy = scene.curvature[:, 1:][scene.present[:, 1:]].unbind(-1)
    determinant = kxx * kyy - kxy.square() / 4  # of the quadratic form: > 0 dome or bowl, < 0 saddle
    planar = (kxx == 0) & (kxy == 0) & (kyy == 0)
    assert 0.3 < planar.float().mean() < 0.7
    assert ((determinant > 0) & (kxx > 0)).any() and ((determinant > 0) & (kxx < 0)).any()
    assert (determinant < 0).any()


def test_scenes_mix_polygons_ellipses_thin_bars_and_holes() -> None:
    scene = SceneGenerator(replace(CLEAN, surfaces=24)).sample_scene(batch_size=8, seed=4)
    foreground = scene.present[:, 1:]
    sides = set(scene.sides[:, 1:][foreground].tolist())
    assert set(range(3, 9)) | {MAX_SIDES} <= sides
    assert scene.has_hole[:, 1:][foreground].any()
    axis_lengths = 1 / scene.to_shape[:, 1:, :, :2].norm(dim=-1)  # shape radii (B, S, 2), px
    aspect = axis_lengths.max(-1).values / axis_lengths.min(-1).values
    assert (aspect[foreground] > 10).any()  # thin bars
    slope = scene.plane[:, 1:, :2].norm(dim=-1)[foreground]
    assert (slope == 0).any() and (slope > 0.05).any()


ROADS = replace(CLEAN, height=96, width=192, road_probability=1.0)


def test_road_scenes_recede_to_a_horizon_under_a_far_sky() -> None:
    generator = SceneGenerator(ROADS)
    scene = generator.sample_scene(batch_size=6, seed=2)
    scene.present[:, 2:] = False  # only the sky and the ground
    disparity = generator.render(scene).disparity[:, 0]  # (B, H, W)
    assert ROADS.max_disparity is not None
    sky = disparity <= 0.02 * ROADS.max_disparity
    ground = ~sky
    assert ground.float().mean() > 0.3 and sky.any()
    # Down each column the disparity never falls: sky above, then the ground nearing the camera.
    assert (disparity[:, 1:] - disparity[:, :-1] >= -1e-4).all()
    # The ground is seen in every scene, and its disparity grows from row to row (a vertical gradient).
    rows_down = (disparity[:, 1:] - disparity[:, :-1])[ground[:, 1:] & ground[:, :-1]]
    assert ground.flatten(1).any(1).all() and rows_down.median() > 0.15
    assert disparity.max() <= ROADS.max_disparity


def things_at_their_centres(scene: Scene) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The foreground things (surfaces 2 on) of layout scenes: their shapes' centres x, y (B, S-2) px
    and their planes' disparity there (B, S-2) px."""
    centre = -torch.linalg.solve(scene.to_shape[:, 2:, :, :2], scene.to_shape[:, 2:, :, 2:])[..., 0]
    x, y = centre.unbind(-1)
    a, b, c = scene.plane[:, 2:].unbind(-1)
    return x, y, a * x + b * y + c


def test_things_in_road_scenes_stand_on_the_ground_at_least_as_near_as_it() -> None:
    scene = SceneGenerator(ROADS).sample_scene(batch_size=6, seed=3)
    ground_a, ground_b, ground_c = scene.plane[:, 1:2].unbind(-1)  # (B, 1) each
    x, y, thing_disparity = things_at_their_centres(scene)
    ground_there = (ground_a * x + ground_b * y + ground_c).clamp(0, 0.9 * ROADS.max_disparity)
    assert (thing_disparity >= ground_there - 1e-3).all()
    assert scene.projective[:, 1].all() and not scene.projective[:, 2:].any()


ROOMS = replace(CLEAN, height=96, width=192, room_probability=1.0)


def test_room_scenes_have_a_floor_meeting_a_textured_back_wall() -> None:
    generator = SceneGenerator(ROOMS)
    scene = generator.sample_scene(batch_size=6, seed=2)
    scene.present[:, 2:] = False  # only the wall and the floor
    disparity = generator.render(scene).disparity[:, 0]  # (B, H, W)
    assert ROOMS.max_disparity is not None
    wall = scene.plane[:, 0, 2]  # (B,) px, fronto-parallel
    assert (scene.plane[:, 0, :2] == 0).all()
    assert ((wall >= 0.1 * ROOMS.max_disparity) & (wall <= 0.45 * ROOMS.max_disparity)).all()
    # The top rows are the wall; down each column the disparity never falls; the floor nears the camera.
    assert torch.allclose(disparity[:, 0], wall[:, None].expand(-1, ROOMS.width))
    assert (disparity[:, 1:] - disparity[:, :-1] >= -1e-4).all()
    floor = disparity > wall[:, None, None] + 1e-3
    assert floor[:, -1].all() and (floor.flatten(1).float().mean(1) > 0.05).all()
    assert disparity.max() <= 0.95 * ROOMS.max_disparity + 1e-3
    # The floor meets the wall: at the row where it starts, its disparity is the wall's.
    first = floor.float().argmax(1)  # (B, W) the floor's first row in each column
    at_junction = disparity.gather(1, first[:, None]).squeeze(1)
    step = scene.plane[:, 1, 1]  # px of disparity per row
    assert ((at_junction - wall[:, None]) <= step[:, None] + 1e-3).all()
    # A wall is textured as any surface is; only skies are weakly textured.
    assert (scene.contrast[:, 0] >= ROOMS.contrast[0]).all()
    assert scene.projective[:, 1].all()


def test_things_in_room_scenes_stand_in_front_of_the_wall() -> None:
    scene = SceneGenerator(ROOMS).sample_scene(batch_size=6, seed=3)
    _, _, thing_disparity = things_at_their_centres(scene)
    assert (thing_disparity >= scene.plane[:, :1, 2] - 1e-3).all()


def test_the_ground_texture_is_seen_in_perspective_twice_as_fine_at_half_the_disparity() -> None:
    generator = SceneGenerator(ROADS)
    scene = generator.sample_scene(batch_size=4, seed=4)
    scene.present[:, 2:] = False
    scene.fade_disparity[:, 1] = 1e-3  # stripes along u vary across rows only: they never alias vertically
    size = ROADS.texture_size
    u = torch.arange(size, dtype=torch.float32).view(1, -1, 1)
    stripes = torch.cos(2 * math.pi * 16 * u / size).expand(size, size, 3)  # 16 periods across the texture, along u
    scene.textures[torch.arange(4), scene.texture[:, 1]] = stripes
    scene.base[:, 1], scene.contrast[:, 1] = 128.0, 100.0
    scene.plane[:, 1, 0] = 0.0  # no roll: a row has one disparity
    scene.ramp.zero_()
    batch = generator.render(scene)
    for n in range(4):
        disparity, grey = batch.disparity[n, 0, :, 0], batch.left[n].mean(0) - 128.0
        near_row = int(disparity.argmax())
        far_row = int((disparity - disparity[near_row] / 2).abs().argmin())
        crossings = [int((grey[row, 1:].sign() != grey[row, :-1].sign()).sum()) for row in (near_row, far_row)]
        expected = float(disparity[near_row] / disparity[far_row])
        assert crossings[1] / crossings[0] == pytest.approx(expected, rel=0.15), (n, crossings, expected)


def test_scale_augmentation_multiplies_every_length_by_the_scale() -> None:
    def lengths(log2_scale: float) -> tuple[torch.Tensor, torch.Tensor]:
        config = replace(CLEAN, log2_scale=(log2_scale, log2_scale))
        scene = SceneGenerator(config).sample_scene(batch_size=2, seed=6)
        shape_axes = 1 / scene.to_shape[:, 1:, :, :2].norm(dim=-1)  # (B, S, 2) shape radii, px
        texel = 1 / scene.to_texture[..., :2].norm(dim=-1)  # (B, S, 2) px per texel
        return shape_axes, texel

    unscaled, doubled = lengths(0.0), lengths(1.0)
    torch.testing.assert_close(doubled[0], 2 * unscaled[0])
    torch.testing.assert_close(doubled[1], 2 * unscaled[1])


def test_images_hold_both_flat_and_strongly_textured_regions() -> None:
    left = SceneGenerator(replace(CLEAN, height=96, width=192)).generate(batch_size=4, seed=9).left
    gradient = (left[..., 1:] - left[..., :-1]).abs().mean(dim=1)
    assert (gradient < 0.5).float().mean() > 0.05
    assert (gradient > 15).float().mean() > 0.05


def one_square_scene(background: float = 10.0, square: float = 30.0, first_column: int = 100) -> Scene:
    """A flat background at disparity `background` (grey 50) and, in front, a square at disparity
    `square` (grey 200) covering columns first_column..first_column + 59 and rows 20..59 of an 80-row
    left view (by default columns 100..159 of an 80 x 200 view)."""

    def pair(background: list[float], square: list[float]) -> torch.Tensor:
        return torch.tensor([[background, square]], dtype=torch.float32)

    no_texture = pair([0.0] * 6, [0.0] * 6).view(1, 2, 2, 3)
    centre = first_column + 29.5
    return Scene(
        plane=pair([0, 0, background], [0, 0, square]),
        curvature=torch.zeros(1, 2, 3),
        apex=torch.zeros(1, 2, 2),
        # Background: everywhere. Square: u = (x - centre) / 30, v = (y - 39.5) / 20.
        to_shape=torch.tensor([[[[0.0, 0, 0], [0, 0, 0]], [[1 / 30, 0, -centre / 30], [0, 1 / 20, -39.5 / 20]]]]),
        sides=torch.tensor([[4, 4]]),
        phase=torch.full((1, 2), math.pi / 4),
        radii=torch.full((1, 2, MAX_SIDES), math.sqrt(2)),  # corners at (+-1, +-1) in the shape frame
        hole=pair([0, 0, 1, 1], [0, 0, 1, 1]),
        has_hole=torch.tensor([[False, False]]),
        present=torch.tensor([[True, True]]),
        texture=torch.zeros(1, 2, dtype=torch.long),
        to_texture=no_texture,
        projective=torch.tensor([[False, False]]),
        fade_disparity=torch.zeros(1, 2),
        base=pair([50] * 3, [200] * 3),
        contrast=torch.zeros(1, 2),
        ramp=torch.zeros(1, 2, 3),
        reflection=torch.zeros(1, 2),
        reflection_depth=torch.zeros(1, 2),
        reflection_texture=torch.zeros(1, 2, dtype=torch.long),
        to_reflection=torch.zeros(1, 2, 2, 3),
        specular=torch.zeros(1, 2),
        shininess=torch.ones(1, 2),
        light=torch.tensor([[0.0, 0.0, -1.0]]),
        ambient=torch.ones(1),
        relief=torch.ones(1),
        camera=torch.tensor([[200.0, 99.5, 39.5]]),
        textures=torch.zeros(1, 1, 4, 4, 3),
    )


def test_occluded_pixels_are_exactly_those_whose_match_is_hidden_or_out_of_frame() -> None:
    batch = SceneGenerator(SceneConfig(height=80, width=200)).render(one_square_scene())
    rows, columns = torch.arange(80).view(-1, 1), torch.arange(200).view(1, -1)
    square_rows = (rows >= 20) & (rows <= 59)
    in_square = square_rows & (columns >= 100) & (columns <= 159)
    assert torch.equal(batch.disparity[0, 0], torch.where(in_square, 30.0, 10.0))
    assert torch.equal(batch.left[0, 0], torch.where(in_square, 200.0, 50.0))
    # The right view shows the square 30 px to the left, over columns 70..129.
    in_right_square = square_rows & (columns >= 70) & (columns <= 129)
    assert torch.equal(batch.right[0, 0], torch.where(in_right_square, 200.0, 50.0))
    # Background pixels 80..99 match right pixels 70..89, which the square hides; columns 0..9
    # match x - 10 < 0, out of the right frame.
    hidden = square_rows & (columns >= 80) & (columns <= 99)
    assert torch.equal(batch.occluded[0, 0], hidden | (columns <= 9))


def test_ground_truth_and_occlusion_stay_exact_at_a_disparity_of_240_px_in_a_512_px_frame() -> None:
    scene = one_square_scene(background=12.0, square=240.0, first_column=400)
    batch = SceneGenerator(SceneConfig(height=80, width=512)).render(scene)
    rows, columns = torch.arange(80).view(-1, 1), torch.arange(512).view(1, -1)
    square_rows = (rows >= 20) & (rows <= 59)
    in_square = square_rows & (columns >= 400) & (columns <= 459)
    assert torch.equal(batch.disparity[0, 0], torch.where(in_square, 240.0, 12.0))
    # The right view shows the square 240 px to the left, over columns 160..219, ...
    in_right_square = square_rows & (columns >= 160) & (columns <= 219)
    assert torch.equal(batch.right[0, 0], torch.where(in_right_square, 200.0, 50.0))
    # ... which hides the matches of background pixels 172..231; columns 0..11 match out of the frame.
    hidden = square_rows & (columns >= 172) & (columns <= 231)
    assert torch.equal(batch.occluded[0, 0], hidden | (columns <= 11))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_generator_runs_and_is_deterministic_on_cuda() -> None:
    generator = SceneGenerator(SMALL, device="cuda")
    first, second = generator.generate(batch_size=2, seed=3), generator.generate(batch_size=2, seed=3)
    assert first.left.device.type == "cuda"
    for name in ("left", "right", "disparity", "occluded"):
        assert torch.equal(getattr(first, name), getattr(second, name)), name
    clean = SceneGenerator(CLEAN, device="cuda").generate(batch_size=2, seed=3)
    visible = (~clean.occluded).expand_as(clean.left).cpu()
    error = (warp_right_to_left(clean.right.cpu(), clean.disparity.cpu()) - clean.left.cpu()).abs()
    assert error[visible].median() < 0.5


def test_photo_textures_are_single_view_photos_never_a_stereo_pair() -> None:
    assert not any("motorcycle" in name or "stereo" in name for name in PHOTOS)
    photos = load_photos(min_side=64, device=torch.device("cpu"))
    assert len(photos) == len(PHOTOS)
    assert all(p.dtype == torch.float32 and p.shape[2] == 3 and min(p.shape[:2]) >= 64 for p in photos)


def test_scenes_with_photo_textures_are_reproducible_and_warp_consistent() -> None:
    config = replace(CLEAN, height=96, width=192, photo_textures=3)
    generator = SceneGenerator(config)
    batch = generator.generate(batch_size=3, seed=5)
    assert torch.equal(batch.left, SceneGenerator(config).generate(batch_size=3, seed=5).left)
    visible = (~batch.occluded).expand_as(batch.left)
    error = (warp_right_to_left(batch.right, batch.disparity) - batch.left).abs()[visible]
    assert error.median() < 0.5
    # the photo slots are drawn: some surface of some scene shows one
    scene = generator.sample_scene(batch_size=3, seed=5)
    procedural = config.texture_count - config.photo_textures
    assert (scene.texture[scene.present] >= procedural).any()


def test_a_panned_scene_is_the_same_scene_shifted_in_both_views_with_its_disparity() -> None:
    generator = SceneGenerator(replace(CLEAN, height=96, width=192, curve_probability=0.5, reflective_probability=0.5))
    scene = generator.sample_scene(batch_size=2, seed=8)
    assert (scene.reflection > 0).any()  # reflections move with the scene too
    before, after = generator.render(scene), generator.render(scene.translated(8.0, 3.0))
    for name in ("left", "right", "disparity"):
        moved, still = getattr(after, name)[..., :-3, :-8], getattr(before, name)[..., 3:, 8:]
        close = ((moved - still).abs() < 0.05).float().mean()
        assert close > 0.995, name  # equal up to float rounding (a rare texel or edge sample flips)


LIT = replace(CLEAN, height=96, width=192, lighting_probability=1.0, curve_probability=0.5)


def test_light_shades_surfaces_by_their_orientation_and_leaves_the_geometry_alone() -> None:
    generator = SceneGenerator(LIT)
    scene = generator.sample_scene(batch_size=2, seed=12)
    lit = generator.render(scene)
    unlit = generator.render(replace(scene, ambient=torch.ones_like(scene.ambient)))
    assert torch.equal(lit.disparity, unlit.disparity) and torch.equal(lit.occluded, unlit.occluded)
    ratio = (lit.left / unlit.left.clamp_min(1.0))[unlit.left > 20]
    assert ratio.max() <= 1.0 + 1e-4 and ratio.min() >= scene.ambient.min() - 1e-3  # a share of the light
    # A slanted plane turned towards the light is brighter than the same plane facing the camera.
    flat = replace(
        scene, plane=scene.plane * torch.tensor([0.0, 0.0, 1.0]), curvature=torch.zeros_like(scene.curvature)
    )
    turned = scene.light[:, :2] / scene.light[:, :2].norm(dim=1, keepdim=True)  # (B, 2)
    towards = replace(
        flat,
        plane=flat.plane + torch.cat([-0.3 * turned, torch.zeros(2, 1)], 1)[:, None] * torch.tensor([1.0, 1.0, 0.0]),
    )
    assert generator.render(towards).left.mean() > generator.render(flat).left.mean()


def test_highlights_differ_between_the_views_while_matte_surfaces_match() -> None:
    glossy_config = replace(LIT, specular_probability=1.0)
    generator = SceneGenerator(glossy_config)
    scene = generator.sample_scene(batch_size=3, seed=13)
    scene = replace(scene, light=torch.tensor([[0.0, 0.0, -1.0]]).expand(3, 3))  # head-on: highlights in view
    glossy = generator.render(scene)
    matte = generator.render(replace(scene, specular=torch.zeros_like(scene.specular)))
    visible = (~glossy.occluded).expand_as(glossy.left)

    def mismatch(batch) -> float:
        return float((warp_right_to_left(batch.right, batch.disparity) - batch.left).abs()[visible].mean())

    assert mismatch(glossy) > 3 * mismatch(matte)  # the views disagree where a highlight is
    assert (glossy.left - matte.left).abs().amax() > 100  # and highlights are bright


def test_vignetting_darkens_the_corners_of_each_view_by_its_own_amount() -> None:
    identity = PhotometricConfig(
        blur_probability=0.0,
        gamma=(1.0, 1.0),
        gain=(1.0, 1.0),
        channel_gain=(1.0, 1.0),
        offset=(0.0, 0.0),
        noise_sigma=(0.0, 0.0),
    )  # changes nothing but what is under test
    plain = replace(SMALL, height=96, width=192, photometric=identity)
    vignetted = replace(plain, photometric=replace(identity, vignetting=0.6))
    before, after = (SceneGenerator(config).generate(batch_size=4, seed=14) for config in (plain, vignetted))
    for view in ("left", "right"):
        ratio = (getattr(after, view) / getattr(before, view).clamp_min(1.0)).mean(dim=1)  # (B, H, W)
        centre, corner = ratio[:, 40:56, 88:104].mean(dim=(1, 2)), ratio[:, :8, :8].mean(dim=(1, 2))
        assert (corner <= centre + 1e-3).all() and (corner < 0.9 * centre).any()
    assert not torch.equal(after.left / before.left.clamp_min(1), after.right / before.right.clamp_min(1))


def test_jpeg_views_carry_compression_artefacts_and_stay_deterministic() -> None:
    plain = replace(SMALL, height=96, width=192)
    jpeg = replace(plain, photometric=replace(PhotometricConfig(), jpeg_probability=1.0))
    before, after = (
        SceneGenerator(plain).generate(batch_size=2, seed=15),
        SceneGenerator(jpeg).generate(batch_size=2, seed=15),
    )
    change = (after.left - before.left).abs()
    assert 0.5 < change.mean() < 12  # lossy, but the same picture
    assert torch.equal(after.left, after.left.round())  # decoded 8-bit values
    assert torch.equal(SceneGenerator(jpeg).generate(batch_size=2, seed=15).right, after.right)
    with pytest.raises(ValueError):
        PhotometricConfig(jpeg_quality=(0, 50))
    with pytest.raises(ValueError):
        PhotometricConfig(vignetting=1.0)


def test_a_pan_is_one_scene_rendered_frame_by_frame_and_its_pairs_are_8_bit_images() -> None:
    generator = SceneGenerator(replace(CLEAN, height=64, width=128))
    frames = generator.pan(seed=16, frames=3, step=(5.0, 1.0))
    scene = generator.sample_scene(batch_size=1, seed=16)
    assert torch.equal(frames[2].left, generator.render(scene.translated(10.0, 2.0)).left)
    left, right = frames[0].pair()
    assert left.dtype == right.dtype == np.uint8 and left.shape == (64, 128, 3)
    assert np.array_equal(left, frames[0].left[0].permute(1, 2, 0).round().to(torch.uint8).numpy())


@pytest.mark.parametrize(
    "layout",
    [
        dict(curve_probability=0.5),
        dict(road_probability=1.0),
        dict(room_probability=1.0),
        dict(thin_probability=0.5, wide_range_probability=1.0, wide_max_disparity=100.0),  # up to 100 of 128 px
    ],
)
def test_the_z_buffer_evaluates_each_surface_only_inside_a_box_that_holds_all_its_points(layout: dict) -> None:
    """Each surface is evaluated only within its box in the view (the renderer's culling): the
    box holds every point the surface covers there, in both views, and the nearest surface then
    equals a z-buffer over every surface at every point."""
    config = replace(SMALL, max_disparity=40.0, **layout)
    scene = SceneGenerator(config).sample_scene(batch_size=2, seed=3)
    x = torch.arange(config.width, dtype=torch.float32).view(1, 1, 1, -1)
    y = torch.arange(config.height, dtype=torch.float32).view(1, 1, -1, 1)
    for view in ("left", "right"):
        x_left = x if view == "left" else seen_from_right(scene, x, y)
        covered = covers(scene, x_left, y) & scene.present[..., None, None]  # (B, S, H, W)
        low_x, high_x, low_y, high_y = (b[..., None, None] for b in view_bounds(scene, view).unbind(-1))
        in_box = (x >= low_x) & (x <= high_x) & (y >= low_y) & (y <= high_y)
        assert covered.any() and not (covered & ~in_box).any()
        bounded = torch.isfinite(low_x) & torch.isfinite(high_x)  # foreground shapes: small boxes
        assert in_box[bounded.expand_as(in_box)].float().mean() < 0.5

        disparity = surface_disparity(
            scene.plane[..., None, None, :],
            scene.curvature[..., None, None, :],
            scene.apex[..., None, None, :],
            x_left,
            y,
        )
        everywhere = torch.where(covered, disparity, -math.inf).max(dim=1, keepdim=True)
        nearest, index, _ = nearest_surface(scene, x, y, view)
        assert torch.equal(index, everywhere.indices)
        # the right view's root, computed on other tensor shapes, may round differently (1e-6 px)
        torch.testing.assert_close(nearest, everywhere.values, rtol=0, atol=0 if view == "left" else 1e-4)


# Hard cases (stereo_data.synthetic.hard_cases): off by default, leaving the recipe's batches as they were.

RECIPE_SUMS = {
    # Sums of (left, right, disparity, occluded) of the batch of 2 of seed 0, recorded before the
    # hard-case options existed (commit 24d8ab0). A deliberate change of the recipe updates them.
    "default": (8739779.124498844, 8885206.14743948, 296983.23085546494, 4416.0),
    "layouts": (4822410.837818973, 3971062.060953174, 344325.7913751602, 5461.0),
}


@pytest.mark.parametrize(
    ("name", "config"),
    [
        ("default", SMALL),
        (
            "layouts",
            replace(
                SMALL,
                road_probability=0.5,
                room_probability=0.5,
                curve_probability=0.5,
                lighting_probability=0.5,
                specular_probability=0.5,
                supersample=2,
            ),
        ),
    ],
)
def test_hard_case_options_at_their_defaults_leave_every_batch_as_it_was(name: str, config: SceneConfig) -> None:
    assert (config.thin_probability, config.flat_probability, config.repetitive_probability) == (0, 0, 0)
    assert config.wide_range_probability == config.reflective_probability == config.row_offset_probability == 0
    batch = SceneGenerator(config).generate(batch_size=2, seed=0)
    sums = [float(getattr(batch, view).double().sum()) for view in ("left", "right", "disparity", "occluded")]
    # Any extra random draw would change whole scenes (sums by percents); allow only float rounding.
    assert sums == pytest.approx(RECIPE_SUMS[name], rel=1e-4), name


def test_wide_max_disparity_defaults_to_256_at_512_px_and_never_below_max_disparity() -> None:
    assert SceneConfig(width=512).wide_max_disparity == 256
    assert SceneConfig(width=1024).wide_max_disparity == 512
    assert SceneConfig(width=512, max_disparity=300).wide_max_disparity == 300


def pixel_grid(config: SceneConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """The left view's pixel centres: x (1, 1, 1, W) and y (1, 1, H, 1), px."""
    x = torch.arange(config.width, dtype=torch.float32).view(1, 1, 1, -1)
    return x, torch.arange(config.height, dtype=torch.float32).view(1, 1, -1, 1)


def narrow_rise(disparity: torch.Tensor, reach: int) -> torch.Tensor:
    """(B, 1, H, W) px: how far each pixel's disparity stands above both of its neighbours `reach` px
    away along x or along y (the larger; 0 within `reach` of the border): the disparity jump across
    a structure narrower than about `reach` px."""
    rise = torch.zeros_like(disparity)
    for dim in (-1, -2):
        size = disparity.shape[dim] - 2 * reach
        before, centre, after = (disparity.narrow(dim, start, size) for start in (0, reach, 2 * reach))
        inner = rise.narrow(dim, reach, size)
        inner.copy_(torch.maximum(inner, centre - torch.maximum(before, after)))
    return rise


THIN = replace(CLEAN, height=96, width=192, thin_probability=1.0)


def test_thin_structures_are_bars_1_to_6_px_wide_far_in_front_of_the_background() -> None:
    generator = SceneGenerator(THIN)
    scene = generator.sample_scene(batch_size=4, seed=5)
    foreground = scene.present[:, 1:]
    half_axes = 1 / scene.to_shape[:, 1:, :, :2].norm(dim=-1)  # (B, S, 2) px
    width, length = 2 * half_axes.amin(-1)[foreground], 2 * half_axes.amax(-1)[foreground]
    assert width.min() >= 1 - 1e-4 and width.max() <= 6 + 1e-4 and (length > 5 * width).all()

    batch = generator.render(scene)
    x, y = pixel_grid(THIN)
    _, surface, _ = nearest_surface(scene, x, y, "left")
    thin = surface > 0
    a, b, c = (part[:, None, None, None] for part in scene.plane[:, 0].unbind(-1))
    above_background = (batch.disparity - (a * x + b * y + c))[thin]
    assert THIN.max_disparity is not None
    quarter = THIN.max_disparity / 4  # (1 - background_max_fraction) / 2 of the largest disparity
    assert thin.float().mean() > 0.02 and above_background.min() >= quarter - 1e-3
    # In the disparity map: regions a few px across that stand far above both of their sides.
    assert (narrow_rise(batch.disparity, 8)[thin] > quarter).float().mean() > 0.5


def test_thin_structures_are_never_broken_into_dashes_in_either_view() -> None:
    """Each bar alone in front of the background: its pixels form one 8-connected piece in each
    view (at least a pixel wide, a bar covers a pixel centre in every row or column it crosses)."""
    generator = SceneGenerator(THIN)
    scene = generator.sample_scene(batch_size=8, seed=6)
    scene.present[:, 2:] = False
    x, y = pixel_grid(THIN)
    for view in ("left", "right"):
        _, surface, _ = nearest_surface(scene, x, y, view)
        for n in range(8):
            bar = (surface[n, 0] == 1).to(torch.uint8).numpy()
            if bar.any():
                pieces, _ = cv2.connectedComponents(bar, connectivity=8)
                assert pieces == 2, (view, n)  # the background label and one piece


def test_wide_range_scenes_reach_past_192_px_at_384_x_512_and_stay_within_the_wide_maximum() -> None:
    config = SceneConfig(height=384, width=512, surfaces=12, texture_size=64, photometric=None)
    config = replace(config, wide_range_probability=1.0)
    assert config.max_disparity == 192 and config.wide_max_disparity == 256
    disparity = SceneGenerator(config).generate(batch_size=4, seed=0).disparity
    assert disparity.min() >= 0 and disparity.max() <= 256
    assert disparity.max() > 192  # about 3 in 4 scenes reach past 192 px


FLAT = replace(CLEAN, height=96, width=192, flat_probability=1.0)


def texture_and_shading(generator: SceneGenerator, scene: Scene) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The left view's grey levels split into texture (grey minus its 7 x 7 mean) and shading (that
    mean), each (B, 1, H, W), and where a 7 x 7 window lies on one surface (B, 1, H, W) bool, with
    the surface index there (outside: -1)."""
    grey = generator.render(scene).left.mean(1, keepdim=True)
    shading = F.avg_pool2d(grey, 7, 1, 3, count_include_pad=False)
    _, surface, _ = nearest_surface(scene, *pixel_grid(generator.config), "left")
    index = surface.float()
    one_surface = F.max_pool2d(index, 7, 1, 3) == -F.max_pool2d(-index, 7, 1, 3)
    return grey - shading, shading, torch.where(one_surface, surface, -1)


def test_flat_surfaces_are_large_weakly_textured_planes_with_slow_shading() -> None:
    generator = SceneGenerator(FLAT)
    scene = generator.sample_scene(batch_size=4, seed=7)
    assert scene.contrast[scene.present].max() <= 4.0 and (scene.curvature == 0).all()
    half_axes = 1 / scene.to_shape[:, 1:, :, :2].norm(dim=-1)  # (B, S, 2) px
    radius = half_axes.prod(-1).sqrt()[scene.present[:, 1:]]  # geometric mean of the half axes
    assert radius.min() >= 0.25 * FLAT.width * 2 ** FLAT.log2_scale[0] - 1e-3

    texture, shading, surface = texture_and_shading(generator, scene)
    plain_scene = SceneGenerator(replace(FLAT, flat_probability=0.0)).sample_scene(batch_size=4, seed=7)
    plain_texture, _, plain_surface = texture_and_shading(generator, plain_scene)
    texture_std = texture[surface >= 0].std()
    assert texture_std < 2  # grey levels
    assert plain_texture[plain_surface >= 0].std() > 2 * texture_std
    for n in range(4):  # the brightness drifts across the largest surface in view, far more than the texture
        largest = surface[n][surface[n] >= 0].mode().values
        brightness = shading[n][surface[n] == largest]
        assert brightness.quantile(0.95) - brightness.quantile(0.05) > 3 * texture_std, n


def secondary_peak(image: torch.Tensor, lags: int = 64) -> tuple[torch.Tensor, torch.Tensor]:
    """The autocorrelation along x of images (B, 3, H, W), normalised and averaged over rows: its
    highest value past the central peak (after its first local minimum), and the first lag past
    that minimum where it comes within 0.05 of that value (a period, not a multiple of it), px;
    each (B,)."""
    grey = image.mean(1)
    grey = grey - grey.mean(-1, keepdim=True)
    width = grey.shape[-1]
    correlation = torch.stack([(grey[..., : width - k] * grey[..., k:]).mean(-1) for k in range(lags)], -1).mean(1)
    correlation = correlation / correlation[:, :1]
    values, where = [], []
    for row in correlation:
        rising = torch.nonzero(row[1:] > row[:-1]).flatten()
        first_minimum = int(rising[0]) if len(rising) else lags - 1
        highest = row[first_minimum:].max()
        values.append(highest)
        where.append(first_minimum + int(torch.nonzero(row[first_minimum:] >= highest - 0.05)[0]))
    return torch.stack(values), torch.tensor(where)


REPETITIVE = replace(CLEAN, height=96, width=192, repetitive_probability=1.0)


def filling_the_frame(scene: Scene) -> Scene:
    """The scenes with their first foreground surface alone, fronto-parallel in front of the
    background and stretched over the whole frame (its shading ramp, drawn for its own extent,
    taken off)."""
    scene.present[:, 1], scene.present[:, 2:], scene.has_hole[:, 1] = True, False, False
    scene.to_shape[:, 1] = 0.0  # a zero map to the shape frame: the surface covers the plane
    assert REPETITIVE.max_disparity is not None
    scene.plane[:, 1] = torch.tensor([0.0, 0.0, REPETITIVE.max_disparity])  # px: nearer than the background
    scene.curvature[:, 1], scene.ramp[:, 1, :2] = 0.0, 0.0
    return scene


def test_repetitive_surfaces_repeat_every_4_to_40_px_along_the_rows() -> None:
    generator = SceneGenerator(REPETITIVE)
    scene = generator.sample_scene(batch_size=6, seed=9)
    foreground = scene.present.clone()
    foreground[:, 0] = False
    assert (scene.texture[foreground] >= REPETITIVE.texture_count).all()  # the repetitive slots
    period = repetitive_period_texels(REPETITIVE.texture_size) / scene.to_texture[foreground][:, 0, :2].norm(dim=-1)
    assert period.min() >= 4 - 1e-3 and period.max() <= 40 + 1e-3  # px

    peak, lag = secondary_peak(generator.render(filling_the_frame(scene)).left)
    assert (peak > 0.6).all()  # a shifted row matches itself again one period on: ambiguous matches
    assert ((lag >= 4) & (lag <= 41)).all()  # the period along the row, 40 px turned by up to 10 degrees
    plain = SceneGenerator(replace(REPETITIVE, repetitive_probability=0.0)).sample_scene(batch_size=6, seed=9)
    plain.present[:, 1:] = False  # the background alone fills the frame
    assert secondary_peak(generator.render(plain).left)[0].median() < 0.3


def test_the_background_is_never_repetitive_so_that_no_scene_is_ambiguous_everywhere() -> None:
    """A pattern repeating along the rows over the whole frame matches itself a period away at
    every pixel but the left border's: no disparity could be learnt from such a scene."""
    scene = SceneGenerator(REPETITIVE).sample_scene(batch_size=6, seed=9)
    assert (scene.texture[:, 0] < REPETITIVE.texture_count).all()
    scene.present[:, 1:] = False  # the background alone
    peak, _ = secondary_peak(SceneGenerator(REPETITIVE).render(scene).left)
    assert peak.median() < 0.3


REFLECTIVE = replace(CLEAN, height=96, width=192, reflective_probability=1.0)


def test_a_reflection_moves_between_the_views_by_its_own_disparity_and_leaves_the_ground_truth_alone() -> None:
    """A reflective surface shows a farther scene over its own texture. With its own texture and
    shading taken off, the right view warped by reflection_depth times the surface's disparity
    gives the left view, where warping it by the surface's disparity does not; the ground truth
    stays the surface's."""
    generator = SceneGenerator(REFLECTIVE)
    scene = generator.sample_scene(batch_size=4, seed=15)
    foreground = scene.present.clone()
    foreground[:, 0] = False
    strength, share = scene.reflection[foreground], scene.reflection_depth[foreground]
    assert strength.min() >= 4 - 1e-3 and strength.max() <= 40 + 1e-3  # grey levels (std)
    assert share.min() >= 0 and share.max() <= 0.8
    mirrored = generator.render(
        replace(scene, contrast=torch.zeros_like(scene.contrast), ramp=torch.zeros_like(scene.ramp))
    )
    matte = generator.render(replace(scene, reflection=torch.zeros_like(scene.reflection)))
    assert torch.equal(mirrored.disparity, matte.disparity) and torch.equal(mirrored.occluded, matte.occluded)

    x, y = pixel_grid(REFLECTIVE)
    _, surface, _ = nearest_surface(scene, x, y, "left")
    reflected_disparity = mirrored.disparity * scene.reflection_depth.gather(1, surface.flatten(1)).view_as(surface)
    # where the right view shows the same (foreground, reflective) surface at x - that disparity too
    _, seen_there, _ = nearest_surface(scene, x - reflected_disparity, y, "right")
    reflecting = ((surface > 0) & (seen_there == surface) & ~mirrored.occluded).expand_as(mirrored.left)
    assert reflecting.float().mean() > 0.1
    by_reflection = (warp_right_to_left(mirrored.right, reflected_disparity) - mirrored.left).abs()[reflecting]
    by_surface = (warp_right_to_left(mirrored.right, mirrored.disparity) - mirrored.left).abs()[reflecting]
    assert by_reflection.median() < 0.5  # exact up to bilinear sampling and the surfaces' edges
    assert by_surface.mean() > 3 * by_reflection.mean()


def test_neither_the_background_nor_thin_structures_reflect() -> None:
    """A reflective background covers the frame: no outline would tell it from its reflection."""
    config = replace(REFLECTIVE, thin_probability=0.5)
    kinds = SurfaceKinds.draw((6, config.surfaces + 1), config, Draw.seeded(16, torch.device("cpu")))
    assert kinds.thin.any() and kinds.reflective.any()
    assert not (kinds.reflective & kinds.thin).any() and not kinds.reflective[:, 0].any()
    scene = SceneGenerator(config).sample_scene(batch_size=6, seed=16)
    assert (scene.reflection[:, 0] == 0).all() and (scene.reflection[:, 1:] > 0).any()
