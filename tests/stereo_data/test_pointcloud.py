"""Point clouds from disparity: geometry, filtering, and binary PLY read back by plyfile."""

import io

import numpy as np
import pytest
from plyfile import PlyData

from crestereo_pp.stereo_data.pointcloud import (
    IMAGE_FRAME,
    METRIC_FRAME,
    DepthRange,
    FocalBaseline,
    decode_ply,
    encode_ply,
    metric_depth,
    point_cloud,
)


def test_metric_points_follow_the_pinhole_model_and_keep_their_colors():
    disparity = np.array([[10.0, 20.0], [0.0, 40.0]], np.float32)  # one pixel without disparity
    left = np.arange(12, dtype=np.uint8).reshape(2, 2, 3)
    points, colors = point_cloud(disparity, left, focal_baseline=FocalBaseline(100.0, 0.5, cx=0.0, cy=0.0))
    z = 100.0 * 0.5 / np.array([10.0, 20.0, 40.0])
    expected = np.stack([np.array([0, 1, 1]) * z / 100.0, np.array([0, 0, 1]) * z / 100.0, z], axis=1)
    np.testing.assert_allclose(points, expected, rtol=1e-6)
    np.testing.assert_array_equal(colors, left.reshape(-1, 3)[[0, 1, 3]])


def test_without_calibration_points_are_in_image_space_and_uncertain_ones_are_dropped():
    disparity = np.full((2, 3), 5.0, np.float32)
    uncertainty = np.array([[0.1, 0.9, 0.2], [0.3, 0.4, 0.95]], np.float32)
    points, _ = point_cloud(disparity, np.zeros((2, 3, 3), np.uint8), uncertainty, max_uncertainty=0.5)
    assert points.tolist() == [[0, 0, 5], [2, 0, 5], [0, 1, 5], [1, 1, 5]]
    with pytest.raises(ValueError, match="needs the uncertainty"):
        point_cloud(disparity, np.zeros((2, 3, 3), np.uint8), max_uncertainty=0.5)


def test_the_ply_is_binary_and_reads_back_with_plyfile():
    points = np.array([[0.5, -1.0, 2.0], [3.0, 4.0, 5.0]], np.float32)
    colors = np.array([[255, 0, 10], [1, 2, 3]], np.uint8)
    data = encode_ply(points, colors, METRIC_FRAME)
    assert data.startswith(b"ply\nformat binary_little_endian 1.0\n")
    assert f"comment {METRIC_FRAME}\n".encode() in data  # units and frame, for whoever opens the file
    vertex = PlyData.read(io.BytesIO(data))["vertex"]
    np.testing.assert_array_equal(np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1), points)
    np.testing.assert_array_equal(np.stack([vertex["red"], vertex["green"], vertex["blue"]], axis=1), colors)


def test_a_ply_written_here_reads_back_whole_with_its_comments_and_any_other_file_is_refused():
    points = np.array([[0.5, -1.0, 2.0], [3.0, 4.0, 5.0], [7.0, 8.0, 9.5]], np.float32)
    colors = np.array([[255, 0, 10], [1, 2, 3], [9, 9, 9]], np.uint8)
    for frame in (METRIC_FRAME, IMAGE_FRAME):
        read = decode_ply(encode_ply(points, colors, frame, ['facts {"model":"lite"}', "second"]))
        np.testing.assert_array_equal(read.points, points)
        np.testing.assert_array_equal(read.colors, colors)
        assert read.frame == frame
        assert read.comments == ['facts {"model":"lite"}', "second"]  # in order, the file's own two left out
    data = encode_ply(points, colors, METRIC_FRAME)
    for other in (b"", b"hello", data[:-1], data.replace(b"comment units", b"comment other")):
        with pytest.raises(ValueError):
            decode_ply(other)


def test_a_ply_comment_is_one_line_of_ascii():
    points, colors = np.zeros((1, 3), np.float32), np.zeros((1, 3), np.uint8)
    for comment in ("two\nlines", "carriage\rreturn", "caf\u00e9"):
        with pytest.raises(ValueError, match="one line of ASCII"):
            encode_ply(points, colors, METRIC_FRAME, [comment])


def test_depth_is_focal_times_baseline_over_disparity_within_its_range():
    disparity = np.array([[10.0, 0.0, -1.0, 0.8, 2.0, np.nan]], np.float32)
    rig = FocalBaseline(700.0, 0.5)
    assert metric_depth(disparity, rig).tolist() == [[35.0, np.inf, np.inf, np.inf, 175.0, np.inf]]
    # 0.8 px passes a 0.5 px floor but lies at 437.5 m, beyond 100 m; 2 px lies at 175 m
    assert metric_depth(disparity, rig, DepthRange(0.5, 100.0)).tolist() == [[35.0] + [np.inf] * 5]


def test_points_at_vanishing_disparity_or_beyond_the_depth_limit_are_left_out():
    disparity = np.array([[0.01, 0.5, 2.0, 50.0]], np.float32)  # 0.01 px is 35 km away on this rig
    left = np.zeros((1, 4, 3), np.uint8)
    rig = FocalBaseline(700.0, 0.5)
    points, _ = point_cloud(disparity, left, focal_baseline=rig)
    assert points[:, 2].tolist() == [175.0, 7.0]  # the default drops disparities at or below 1 px
    points, _ = point_cloud(disparity, left, focal_baseline=rig, limits=DepthRange(0.0, 100.0))
    assert points[:, 2].tolist() == [7.0]
    points, _ = point_cloud(disparity, left, limits=DepthRange(0.0, 100.0))  # image space: no depth limit
    assert len(points) == 4
    with pytest.raises(ValueError):
        DepthRange(-1.0)
    assert IMAGE_FRAME != METRIC_FRAME
