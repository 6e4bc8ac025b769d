"""Spec of stereo_data.rig: a raw pair from a calibrated camera, rectified so that matches lie on
one row at the disparity its geometry predicts, maps brought back to the original left pixels;
calibrations read from exactly what OpenCV and ROS write, in well under a millisecond, and every
other or unusable calibration refused with the field named."""

import json
import time

import cv2
import numpy as np
import pytest
from raw_camera import (
    D1,
    D2,
    HANG,
    HEIGHT,
    K1,
    K2,
    MALFORMED,
    PLANE_Z,
    WIDTH,
    R,
    T,
    opencv_file,
    opencv_yaml_with,
    raw_view,
    ros_camera_info_files,
)

from crestereo_pp.stereo_data.rig import MAX_TURN_DEGREES, Rectifier, RigError, StereoRig, parse_rig, read_rig


def test_a_raw_pair_is_rectified_onto_rows_at_the_disparity_its_geometry_gives(tmp_path):
    rig = read_rig(opencv_file(tmp_path / "stereo.yaml"))
    left_raw, right_raw = raw_view(K1, D1, np.eye(3), np.zeros(3)), raw_view(K2, D2, R, T)
    rectifier = Rectifier(rig)
    left, right = rectifier.rectify(left_raw, right_raw)
    # The plane's disparity at each rectified left pixel: depth in the rectified frame, f * B / Z.
    xs, ys = np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT))
    p1 = rig.p1
    rays = np.stack([(xs - p1[0, 2]) / p1[0, 0], (ys - p1[1, 2]) / p1[1, 1], np.ones_like(xs, float)], -1)
    in_left = rays @ rig.r1  # R1.T @ ray, per pixel: the ray in the unrectified left frame
    depth = PLANE_Z / in_left[..., 2]  # rectified-frame depth of the plane point (R1 keeps lengths)
    disparity = (rig.focal_px * rig.baseline / depth).astype(np.float32)
    assert rig.baseline == pytest.approx(np.linalg.norm(T))

    def matched(shift_rows: float) -> float:
        """Mean |left - right at (x - d, y + shift_rows)| over the middle of the image."""
        warped = cv2.remap(
            right, (xs - disparity).astype(np.float32), (ys + shift_rows).astype(np.float32), cv2.INTER_LINEAR
        )
        middle = (slice(40, HEIGHT - 40), slice(80, WIDTH - 40))
        return float(np.abs(warped - left)[middle].mean())

    assert matched(0) < 1.5  # grey levels: interpolation only
    assert matched(2) > 5 * matched(0) and matched(-2) > 5 * matched(0)  # off the row, no match
    raw_error = np.abs(
        cv2.remap(right_raw, (xs - disparity).astype(np.float32), ys.astype(np.float32), cv2.INTER_LINEAR) - left_raw
    )
    assert raw_error[40:-40, 80:-40].mean() > 5 * matched(0)  # the raw pair does not line up


def test_maps_come_back_to_the_original_left_pixels_and_nan_where_there_is_no_counterpart(tmp_path):
    rectifier = Rectifier(read_rig(opencv_file(tmp_path / "stereo.json")))
    xs = np.tile(np.arange(WIDTH, dtype=np.float32), (HEIGHT, 1))  # a map whose value is its rectified x
    back = rectifier.to_original(xs)
    map_x, map_y = rectifier._maps[0]  # rectified pixel -> where it comes from in the original left image
    rows, columns = np.mgrid[20 : HEIGHT - 20 : 7, 20 : WIDTH - 20 : 7]
    original_x, original_y = map_x[rows, columns], map_y[rows, columns]
    inside = (original_x >= 0) & (original_x < WIDTH - 1) & (original_y >= 0) & (original_y < HEIGHT - 1)
    found = back[np.round(original_y[inside]).astype(int), np.round(original_x[inside]).astype(int)]
    assert np.abs(found - columns[inside]).max() < 1.0  # rounding to the pixel grid: under 1 px
    assert np.isnan(back).any() and np.isfinite(back).mean() > 0.8


def test_under_an_identity_calibration_the_original_frame_is_the_rectified_one_to_the_last_row_and_column(tmp_path):
    k = np.array([[400.0, 0, 158], [0, 400.0, 121], [0, 0, 1]])
    straight = {"K1": k, "K2": k, "D1": np.zeros(5), "D2": np.zeros(5), "R": np.eye(3), "T": np.array([-0.12, 0, 0])}
    rectifier = Rectifier(read_rig(opencv_file(tmp_path / "stereo.yaml", **straight)))
    np.testing.assert_allclose(rectifier.rig.p1[:, :3], k, rtol=1e-6)
    maps = np.random.default_rng(0).uniform(0.5, 60.0, (HEIGHT, WIDTH)).astype(np.float32)
    # equal to the interpolation's rounding (stereoRectify moves the focal length by 3e-8), the last row and column too
    np.testing.assert_allclose(rectifier.to_original(maps), maps, atol=1e-3)
    np.testing.assert_allclose(rectifier.to_original_depth(maps), maps, atol=1e-3)


def test_the_rectified_camera_gives_the_metric_depth_focal_length_and_baseline(tmp_path):
    rectifier = Rectifier(read_rig(opencv_file(tmp_path / "stereo.yaml")))
    camera = rectifier.focal_baseline
    assert camera.baseline_m == pytest.approx(0.12, abs=1e-3) and 380 < camera.focal_px < 440
    assert 0 < camera.cx < WIDTH and 0 < camera.cy < HEIGHT


ROS_LEFT = """image_width: 320
image_height: 240
camera_name: left
camera_matrix: {rows: 3, cols: 3, data: [400, 0, 160, 0, 400, 120, 0, 0, 1]}
distortion_model: plumb_bob
distortion_coefficients: {rows: 1, cols: 5, data: [-0.1, 0.04, 0, 0, 0]}
rectification_matrix: {rows: 3, cols: 3, data: [1, 0, 0, 0, 1, 0, 0, 0, 1]}
projection_matrix: {rows: 3, cols: 4, data: [390, 0, 160, 0, 0, 390, 120, 0, 0, 0, 1, 0]}
"""


ROS_RIGHT = ROS_LEFT.replace("camera_name: left", "camera_name: right").replace(
    "data: [390, 0, 160, 0,", "data: [390, 0, 160, -46.8,"
)


def test_a_pair_of_ros_camera_info_files_is_used_with_its_own_rectification(tmp_path):
    (tmp_path / "left.yaml").write_text(ROS_LEFT)
    (tmp_path / "right.yaml").write_text(ROS_RIGHT)
    rig = read_rig([tmp_path / "left.yaml", tmp_path / "right.yaml"])
    assert (rig.image_size, rig.focal_px, rig.baseline) == ((320, 240), 390.0, pytest.approx(0.12))
    with pytest.raises(RigError) as refused:
        parse_rig(ROS_LEFT, ROS_LEFT)  # two left cameras: no baseline
    assert refused.value.field == "right.projection_matrix"


@pytest.mark.parametrize(
    ("entries", "field"),
    [
        ({"K1": None}, "K1"),
        ({"D2": np.zeros(3)}, "D2"),
        ({"R": np.eye(2)}, "R"),
        ({"R": 2 * np.eye(3)}, "R"),
        ({"T": np.array([-0.1, np.nan, 0.0])}, "T"),
        ({"T": np.zeros(3)}, "T"),
        ({"T": np.array([0.0, -0.12, 0.0])}, "T"),  # one camera above the other
        ({"T": np.array([0.12, 0.0, 0.0])}, "T"),  # left and right swapped
        ({"K2": np.zeros((3, 3))}, "K2"),
        ({"image_width": None}, "image_size"),
        ({"image_width": -5}, "image_size"),
        ({"T": np.array([-1e300, 0.0, 0.0])}, "T"),  # focal x baseline beyond what a query may give
        ({"T": np.array([-1e-300, 0.0, 0.0])}, "T"),  # its length underflows: OpenCV's rectification would assert
        ({"T": np.array([-1e-150, 0.0, 0.0])}, "T"),  # depth below the smallest float32: every depth 0 m
        ({"R": 1e300 * np.eye(3)}, "R"),
        ({"R": cv2.Rodrigues(np.array([0.0, np.pi / 2, 0.0]))[0]}, "R"),  # turned 90 degrees: nothing overlaps
        ({"R": cv2.Rodrigues(np.array([0.0, np.radians(MAX_TURN_DEGREES + 5), 0.0]))[0]}, "R"),
        # What OpenCV would rectify, but no camera has: the usual mistakes, each a silent wrong depth
        ({"K1": np.array([[1e12, 0, 158], [0, 1e12, 121], [0, 0, 1]])}, "K1"),  # a field of view of 1e-8 degrees
        ({"K2": np.array([[5.0, 0, 163], [0, 5.0, 118], [0, 0, 1]])}, "K2"),  # wider than a pinhole model reaches
        ({"D1": np.array([50.0, -80.0, 0.0, 0.0, 0.0])}, "calibration"),  # rectified into a 9x enlarged sliver
        ({"T": 1000 * T}, "T"),  # millimetres: every depth 1000 times too far
        ({"T": np.array([-1e-12, 0.0, 0.0])}, "T"),  # two cameras in one place: depths of picometres
    ],
)
def test_an_unusable_calibration_is_refused_naming_the_field(tmp_path, entries, field):
    with pytest.raises(RigError) as refused:
        read_rig(opencv_file(tmp_path / "stereo.yaml", **entries))
    assert refused.value.field == field and str(refused.value).startswith(f"{field}: ")


@pytest.mark.parametrize(
    ("side", "old", "new", "field"),
    [
        (
            "left",
            "data: [1, 0, 0, 0, 1, 0, 0, 0, 1]",
            "data: [1e300, 0, 0, 0, 1e300, 0, 0, 0, 1e300]",
            "rectification_matrix",
        ),
        ("right", "data: [1, 0, 0, 0, 1, 0, 0, 0, 1]", "data: [0, 0, 1, 0, 1, 0, -1, 0, 0]", "rectification_matrix"),
        ("right", "-46.8,", "-3.9e302,", "projection_matrix"),  # a baseline of 1e300 m
        ("right", "-46.8,", "-3.9e-298,", "projection_matrix"),  # a baseline of 1e-300 m
        ("right", "data: [390, 0, 160, -46.8, 0, 390,", "data: [0, 0, 160, -46.8, 0, 390,", "projection_matrix"),
        ("right", "-46.8,", "-46800,", "projection_matrix"),  # a baseline in millimetres: 120 "m"
        ("right", "-46.8,", "-3.9e-10,", "projection_matrix"),  # a baseline of 1e-12 m
        ("left", "data: [400, 0, 160, 0, 400, 120,", "data: [4e7, 0, 160, 0, 4e7, 120,", "camera_matrix"),
    ],
)
def test_a_degenerate_ros_camera_info_is_refused_naming_the_side_and_entry(side, old, new, field):
    texts = {"left": ROS_LEFT, "right": ROS_RIGHT}
    assert old in texts[side]
    texts[side] = texts[side].replace(old, new)
    with pytest.raises(RigError) as refused:
        parse_rig(texts["left"], texts["right"])
    assert refused.value.field == f"{side}.{field}"


def test_a_calibration_in_millimetres_is_refused_saying_t_is_in_metres(tmp_path):
    message = r"^T: a baseline of 120\.0[0-9]* m; at most 10 m: T is in metres .* divide it by 1000"
    with pytest.raises(RigError, match=message):
        read_rig(opencv_file(tmp_path / "stereo.yaml", T=1000 * T))


def test_ros_camera_info_files_given_right_camera_first_are_refused_as_swapped(tmp_path):
    left, right = (path.read_text() for path in ros_camera_info_files(tmp_path))
    with pytest.raises(RigError) as swapped:
        parse_rig(right, left)
    right_p = parse_rig(left, right).p2
    assert swapped.value.field == "calibration"
    assert swapped.value.reason == (
        f"the files look swapped: the first camera_info is a right camera's (projection_matrix P[0][3] = "
        f"{right_p[0, 3]:.4g}, -fx x baseline) and the second a left camera's (P[0][3] = 0); send the left "
        "camera's first, then the right camera's"
    )


@pytest.mark.parametrize("text", ["", "\n\n", "# only a comment\n", "%YAML:1.0\n---\n", "{}"])
def test_an_empty_calibration_file_is_refused_as_empty(text):
    for texts, field in (((text,), "calibration"), ((text, text), "left camera_info")):
        with pytest.raises(RigError) as refused:
            parse_rig(*texts)
        assert (refused.value.field, refused.value.reason) == (field, "the file is empty (no calibration entries)")


def test_one_ros_camera_info_alone_is_refused_asking_for_both_cameras():
    with pytest.raises(RigError, match="one ROS camera_info, which describes one camera: give the left camera's and"):
        parse_rig(ROS_LEFT)


def test_every_form_opencv_writes_a_calibration_in_is_read_from_yaml_and_json(tmp_path):
    """Matrices (2-D, and 1-D as nd-matrices), float32 and integer ones, R as a rotation vector,
    image_size as a sequence, strings, numbers and comments beside them, the old %YAML:1.0 header."""
    rigs = {}
    for suffix in ("yaml", "json"):
        path = tmp_path / f"stereo.{suffix}"
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
        storage.writeComment("a stereo camera")
        storage.write("calibration_time", "Mon Jan  1 10:00:00 2024")
        storage.write("K1", K1)
        storage.write("D1", D1)  # 1-D: an opencv-nd-matrix
        storage.write("K2", K2.astype(np.float32))
        storage.write("D2", D2.reshape(1, 5))
        storage.write("R", cv2.Rodrigues(R)[0] if suffix == "json" else R)
        storage.write("T", T.reshape(3, 1))
        storage.startWriteStruct("image_size", cv2.FileNode_SEQ)  # YAML: a block of `- n` lines
        storage.write("", WIDTH)
        storage.write("", HEIGHT)
        storage.endWriteStruct()
        storage.write("rms", 0.31)
        storage.write("camera", "left right")
        storage.write("corners", np.arange(6, dtype=np.int32).reshape(2, 3))
        storage.release()
        rigs[suffix] = read_rig(path)
    yaml_text = (tmp_path / "stereo.yaml").read_text()
    assert yaml_text.startswith("%YAML 1.2\n---\n") and "\n   - 320\n" in yaml_text
    rigs["old header"] = parse_rig(yaml_text.replace("%YAML 1.2", "%YAML:1.0"))
    for rig in rigs.values():
        assert rig.image_size == (WIDTH, HEIGHT)
        assert np.array_equal(rig.k1, K1) and np.array_equal(rig.d2, D2) and np.allclose(rig.k2, K2)
        assert rig.baseline == pytest.approx(np.linalg.norm(T))
        np.testing.assert_allclose(rig.p2, rigs["yaml"].p2, rtol=1e-6)
        np.testing.assert_allclose(rig.r1, rigs["yaml"].r1, atol=1e-6)


def test_ros_camera_info_files_as_camera_calibration_writes_them_are_the_opencv_rig(tmp_path):
    ros = read_rig(ros_camera_info_files(tmp_path))
    opencv = read_rig(opencv_file(tmp_path / "stereo.yaml"))
    for name in ("k1", "d1", "k2", "d2", "r1", "r2", "p1", "p2"):
        np.testing.assert_allclose(getattr(ros, name), getattr(opencv, name), rtol=1e-12, atol=1e-12)


def test_a_binary_scalar_that_held_opencvs_parser_for_seconds_is_refused_at_once():
    started = time.perf_counter()
    with pytest.raises(RigError) as refused:
        parse_rig(HANG)
    assert time.perf_counter() - started < 0.05  # OpenCV's cv2.FileStorage: 10-22 s
    assert refused.value.field == "K1" and "!!binary" in refused.value.reason


@pytest.mark.parametrize(("key", "text", "field"), list(MALFORMED.values()), ids=list(MALFORMED))
def test_a_malformed_calibration_is_refused_naming_the_entry(tmp_path, key, text, field):
    with pytest.raises(RigError) as refused:
        parse_rig(opencv_yaml_with(tmp_path / "c.yaml", key, text))
    assert refused.value.field == field


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("%YAML:1.0\nK1: [1, 2]\n", "calibration"),  # no --- after the header
        ("K1:\n  rows: 3\n    cols: 3\n", "K1"),  # indentation of no matrix
        ("T: [-0.12, 0, 0]\nT: [-0.12, 0, 0]\n", "T"),  # twice
        ("T: [-0.12, [0], 0]\n", "T"),  # a list in a list
        ("T: [-0.12, .Nan, 0]\n", "T"),
        ("T: [-0.12, 0, 0,]\n", "T"),
        ("K1: {rows: 3, cols: 3, dt: d, data: [1, 0, 0, 0, 1, 0, 0, 0, 1], more: 1}\n", "K1"),
        ("K1: !!opencv-matrix\n   rows: 3\n   cols: 3\n   data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n", "K1"),  # no dt
        ("  K1: [1, 2]\n", "calibration"),
        ("- 1\n- 2\n", "calibration"),
        ("\n" * 1001, "calibration"),  # more lines than a calibration has
        ('{"T": [-0.12, NaN, 0]}', "calibration"),
        ('{"T": [-0.12, 1e309, 0]}', "T"),
        ('{"T": [-0.12, "0", 0]}', "T"),
        ('{"image_width": true}', "image_width"),
        ('{"T": {"type_id": "opencv-matrix", "rows": 3, "cols": 1, "dt": "d", "data": [[1], [2], [3]]}}', "T"),
        ('{"T": {"type_id": "opencv-nd-matrix", "sizes": [3, 1, 1], "dt": "d", "data": [1, 2, 3]}}', "T"),
        ('{"T": {"rows": 3, "cols": 1, "dt": "d", "data": [1, 2, 3]}}', "T"),
        ('{"T": [1, 2, 3], "T": [1, 2, 3]}', "calibration"),
        ("[1, 2]", "calibration"),
    ],
)
def test_a_file_outside_the_grammar_opencv_and_ros_write_is_refused(text, field):
    with pytest.raises(RigError) as refused:
        parse_rig(text)
    assert refused.value.field == field


def test_a_pair_of_another_size_or_a_file_that_is_not_a_calibration_is_refused(tmp_path):
    rectifier = Rectifier(read_rig(opencv_file(tmp_path / "stereo.yaml")))
    with pytest.raises(RigError, match="for 320x240 images, the left image is 640x480"):
        rectifier.rectify(np.zeros((480, 640, 3), np.uint8), np.zeros((480, 640, 3), np.uint8))
    with pytest.raises(RigError, match="calibration: not a YAML or JSON file"):
        parse_rig("\x00\x01 not yaml {[")


def test_a_rig_travels_as_json_exactly_and_json_that_is_not_a_rig_is_refused(tmp_path):
    rig = read_rig(opencv_file(tmp_path / "stereo.yaml"))
    again = StereoRig.from_json(rig.to_json())
    assert again.image_size == rig.image_size
    for name in ("k1", "d1", "k2", "d2", "r1", "r2", "p1", "p2"):
        assert np.array_equal(getattr(again, name), getattr(rig, name)), name
    values = json.loads(rig.to_json())
    for change, field in (
        ({"p1": [[1.0, 2.0]]}, "p1"),
        ({"k2": [[float("nan")] * 3] * 3}, "k2"),
        ({"image_size": [320.5, 240]}, "image_size"),
        ({"p2": (np.asarray(values["p2"]) * [[1, 1, 1, -1], [1, 1, 1, 1], [1, 1, 1, 1]]).tolist()}, "calibration"),
    ):
        with pytest.raises(RigError) as refused:
            StereoRig.from_json(json.dumps({**values, **change}))
        assert refused.value.field == field
    with pytest.raises(RigError, match="calibration: not a rig"):
        StereoRig.from_json("[1, 2]")
