"""Procedural pairs off their rows (`SceneConfig.row_offset_probability`): the right view moved by
a plane of vertical offsets, as an imperfect rectification leaves a real pair, with the left view
and the horizontal ground truth exactly as rendered."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from crestereo_pp.inference.row_alignment import RowOffset, measure_row_offset
from crestereo_pp.stereo_data.synthetic import SceneConfig, SceneGenerator
from crestereo_pp.stereo_data.synthetic.draw import Draw
from crestereo_pp.stereo_data.synthetic.rectification import draw_row_offsets, offset_rows

CLEAN = SceneConfig(height=192, width=256, surfaces=12, min_surfaces=6, texture_size=64, photometric=None)


def corner_offsets(planes: torch.Tensor) -> torch.Tensor:
    """(B, 4) dy px at the frame's four corners of the planes (B, 3)."""
    centre, across, down = planes.unbind(-1)
    return torch.stack([centre + sx * across / 2 + sy * down / 2 for sx in (-1, 1) for sy in (-1, 1)], -1)


def test_a_right_view_moved_one_row_down_shows_each_row_one_lower_and_repeats_its_top_row() -> None:
    image = torch.rand(2, 3, 16, 24, generator=torch.Generator().manual_seed(0)) * 255
    planes = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    moved = offset_rows(image, planes)
    torch.testing.assert_close(moved[0, :, 1:], image[0, :, :-1], atol=1e-3, rtol=0)
    torch.testing.assert_close(moved[0, :, 0], image[0, :, 0], atol=1e-3, rtol=0)
    assert torch.equal(moved[1], image[1])  # a zero plane leaves its sample bit for bit


def test_a_tilted_plane_moves_each_column_by_its_own_offset() -> None:
    width = 33
    image = torch.arange(20, dtype=torch.float32).view(1, 1, 20, 1).expand(1, 1, 20, width).clone()  # value = row
    moved = offset_rows(image, torch.tensor([[0.0, 2.0, 0.0]]))  # dy from -1 px (left edge) to ~+1 px (right)
    dy = 2.0 * (torch.arange(width) / width - 0.5)
    inner = moved[0, 0, 5:15]  # rows whose source lies inside the frame
    torch.testing.assert_close(inner, torch.arange(5, 15.0).view(-1, 1) - dy.view(1, -1), atol=1e-4, rtol=0)


def test_a_share_of_the_pairs_is_drawn_off_its_rows_and_never_beyond_row_offset() -> None:
    config = replace(CLEAN, row_offset_probability=0.4, row_offset=1.5)
    planes = draw_row_offsets(4000, config, Draw.seeded(3, torch.device("cpu")))
    moved = planes.ne(0).any(-1)
    assert 0.36 < moved.float().mean() < 0.44
    corners = corner_offsets(planes).abs().amax(-1)
    assert corners.max() <= 1.5 + 1e-6 and corners[moved].max() > 1.3  # the whole range is drawn
    assert corners[moved].min() < 0.2  # and nearly aligned pairs too


def test_pairs_off_their_rows_keep_the_left_view_and_ground_truth_and_show_the_drawn_plane() -> None:
    """The right view off its rows is the aligned one moved by the plane the batch reports, in the
    convention row alignment measures (`RowOffset`: the match lies dy lower)."""
    aligned = SceneGenerator(CLEAN).generate(batch_size=6, seed=11)
    off = SceneGenerator(replace(CLEAN, row_offset_probability=1.0, row_offset=2.0)).generate(batch_size=6, seed=11)
    assert aligned.row_offset is None and off.row_offset is not None
    for view in ("left", "disparity", "occluded"):
        assert torch.equal(getattr(off, view), getattr(aligned, view)), view
    for index in range(6):
        (_, as_rendered), (_, moved) = aligned.pair(index), off.pair(index)
        measured = measure_row_offset(as_rendered, moved)
        assert measured is not None
        drawn = RowOffset(*off.row_offset[index].tolist(), tracks=0)
        error = np.abs(measured.offsets(*moved.shape[:2]) - drawn.offsets(*moved.shape[:2]))
        assert error.max() < 0.15 and drawn.largest_px > 0.25, (index, measured, drawn)


@pytest.mark.parametrize("probability", [0.0, 1.0])
def test_the_generator_trained_with_row_offsets_runs_on_any_probability(probability: float) -> None:
    batch = SceneGenerator(replace(CLEAN, row_offset_probability=probability)).generate(batch_size=2, seed=5)
    assert batch.right.shape == batch.left.shape and torch.isfinite(batch.right).all()
    assert 0 <= float(batch.right.min()) and float(batch.right.max()) <= 255
