"""Spec of stereo_data.calibration_files on ROS camera_info files: read by PyYAML's safe loader in
any YAML style (camera_calibration's flow style, yaml.safe_dump's block style, a CameraInfo message
as `ros2 topic echo` or ROS 1's `rostopic echo` print it, JSON) to the same rig; a file of neither
form, and an OpenCV file given with a ROS one, refused saying what to send; a YAML alias bomb
refused at once. The calibrations are the repository's own: raw_camera's camera_info files (as
camera_calibration writes them) and the raw example's OpenCV calibration."""

import json
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from raw_camera import ros_camera_info_files

from crestereo_pp.stereo_data.calibration_files import MAX_CALIBRATION_BYTES, parse_entries
from crestereo_pp.stereo_data.rig import RigError, StereoRig, parse_rig, read_rig

EXAMPLE = Path(__file__).parents[2] / "service" / "static" / "examples" / "raw-320x240" / "stereo.yaml"
"""The raw example's calibration (OpenCV's YAML), whose rig the ROS files below are made of too."""
ARRAYS = ("k1", "d1", "k2", "d2", "r1", "r2", "p1", "p2")
SENT_AS = "send one OpenCV calibration file, or two ROS camera_info files (the left camera's, then the right camera's)"


def assert_same_rig(rig: StereoRig, expected: StereoRig) -> None:
    assert rig.image_size == expected.image_size
    for name in ARRAYS:
        assert np.array_equal(getattr(rig, name), getattr(expected, name)), name


def camera_infos(rig: StereoRig) -> list[dict]:
    """The rig as two camera_info maps with camera_calibration's names (left, right)."""

    def matrix(values: np.ndarray) -> dict:
        rows, cols = values.shape if values.ndim == 2 else (1, values.size)
        return {"rows": rows, "cols": cols, "data": values.ravel().tolist()}

    width, height = rig.image_size
    return [
        {
            "image_width": width,
            "image_height": height,
            "camera_name": side,
            "camera_matrix": matrix(k),
            "distortion_model": "plumb_bob",
            "distortion_coefficients": matrix(d),
            "rectification_matrix": matrix(r),
            "projection_matrix": matrix(p),
        }
        for side, k, d, r, p in (("left", rig.k1, rig.d1, rig.r1, rig.p1), ("right", rig.k2, rig.d2, rig.r2, rig.p2))
    ]


def camera_info_message(info: dict, ros: int) -> dict:
    """A camera_info map as the sensor_msgs/CameraInfo message of ROS 2 (d, k, r, p) or ROS 1 (D, K, R, P)."""
    d, k, r, p = "dkrp" if ros == 2 else "DKRP"
    stamp = {"sec": 1718000000, "nanosec": 250} if ros == 2 else {"secs": 1718000000, "nsecs": 250}
    return {
        "header": {**({"seq": 7} if ros == 1 else {}), "stamp": stamp, "frame_id": f"{info['camera_name']}_optical"},
        "height": info["image_height"],
        "width": info["image_width"],
        "distortion_model": info["distortion_model"],
        d: info["distortion_coefficients"]["data"],
        k: info["camera_matrix"]["data"],
        r: info["rectification_matrix"]["data"],
        p: info["projection_matrix"]["data"],
        "binning_x": 0,
        "binning_y": 0,
        "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
    }


@pytest.fixture
def flow_files(tmp_path) -> tuple[str, str]:
    """raw_camera's camera_info files, in camera_calibration's flow style (`data: [...]`)."""
    left, right = ros_camera_info_files(tmp_path)
    return left.read_text(), right.read_text()


def test_block_style_camera_info_files_as_yaml_safe_dump_writes_them_are_the_flow_style_rig(flow_files):
    flow_rig = parse_rig(*flow_files)
    block = [yaml.safe_dump(yaml.safe_load(text)) for text in flow_files]
    assert "data:\n  - " in block[0] and "[" not in block[0]  # block lists: `data:` then `- 400.0` lines
    assert_same_rig(parse_rig(*block), flow_rig)


@pytest.mark.parametrize("style", ["block", "flow", "camera_calibration"])
def test_the_raw_examples_calibration_as_camera_info_files_of_any_yaml_style_is_its_rig(style):
    example = read_rig(EXAMPLE)
    dump = {"block": {}, "flow": {"default_flow_style": True}, "camera_calibration": {"default_flow_style": None}}
    texts = [yaml.safe_dump(info, sort_keys=False, **dump[style]) for info in camera_infos(example)]
    assert_same_rig(parse_rig(*texts), example)


@pytest.mark.parametrize(
    "form",
    ["ros2 topic echo", "ros2 topic echo --flow-style", "rostopic echo (ROS 1)", "JSON (rosbridge)"],
)
def test_a_camera_info_message_as_ros_prints_it_is_the_rig_of_its_camera_info_files(flow_files, form):
    infos = [yaml.safe_load(text) for text in flow_files]
    messages = [camera_info_message(info, 1 if "ROS 1" in form else 2) for info in infos]
    if form == "ros2 topic echo":
        texts = [yaml.safe_dump(message, sort_keys=False) + "---\n" for message in messages]
        assert texts[0].startswith("header:\n  stamp:\n    sec: 1718000000\n") and "\nk:\n- 400.0\n" in texts[0]
    elif form == "JSON (rosbridge)":
        texts = [json.dumps(message) for message in messages]
    else:
        flow = None if "ROS 1" in form else True
        texts = [yaml.safe_dump(message, sort_keys=False, default_flow_style=flow) for message in messages]
    assert_same_rig(parse_rig(*texts), parse_rig(*flow_files))


def test_one_camera_info_message_alone_is_refused_asking_for_both_cameras(flow_files):
    message = yaml.safe_dump(camera_info_message(yaml.safe_load(flow_files[0]), 2)) + "---\n"
    with pytest.raises(RigError, match="one ROS camera_info, which describes one camera: give the left camera's and"):
        parse_rig(message)


def test_an_opencv_file_and_a_camera_info_file_are_refused_saying_what_to_send(flow_files):
    opencv = EXAMPLE.read_text()
    found = "an OpenCV calibration (K1, D1, K2, D2, R, T, image_width, image_height), not a ROS camera_info"
    for texts, field in (((opencv, flow_files[1]), "left camera_info"), ((flow_files[0], opencv), "right camera_info")):
        with pytest.raises(RigError) as refused:
            parse_rig(*texts)
        assert (refused.value.field, refused.value.reason) == (field, f"{found}: {SENT_AS}")


@pytest.mark.parametrize(
    ("text", "found"),
    [
        ("services:\n  web:\n    image: nginx\n    ports: ['8000:8000']\n", "its entries are services"),
        ("name: left camera\nserial: 1234\nfps: 30\n", "its entries are name, serial, fps"),
        ("- image_width\n- 320\n", "a YAML value that is not a map of named entries"),
        ('{"camera": {"fx": 400, "fy": 400}}', "its entries are camera"),
    ],
    ids=["docker compose", "flat", "a list", "JSON"],
)
def test_a_file_that_is_no_calibration_is_refused_naming_the_forms_read(flow_files, text, found):
    for texts, field in (((text,), "calibration"), ((text, flow_files[1]), "left camera_info")):
        with pytest.raises(RigError) as refused:
            parse_rig(*texts)
        reason = refused.value.reason
        assert refused.value.field == field
        assert reason.startswith(f"neither an OpenCV calibration nor a ROS camera_info ({found}): send one OpenCV")
        for named in (
            "cv2.FileStorage",
            "K1, D1, K2, D2, R, T",
            "camera_calibration",
            "camera_matrix",
            "ros2 topic echo",
        ):
            assert named in reason, named


def test_a_billion_laughs_camera_info_of_256_kib_is_refused_at_once(flow_files):
    """PyYAML's safe_load shares an aliased value rather than copying it, so loading such a file
    takes under a millisecond; but its `k` then reads as nested lists of 9^9 numbers (np.asarray
    would ask for 2.9 GB): a camera_info's aliases are refused before anything is read."""
    levels = ["a0: &a0 [" + ", ".join(["1.0"] * 9) + "]"]
    levels += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 9) + "]" for i in range(1, 9)]
    padding = "header: {frame_id: " + "x" * (MAX_CALIBRATION_BYTES - 1000) + "}"
    bomb = "\n".join(["height: 240", "width: 320", padding, *levels, "k: *a8", ""])
    assert MAX_CALIBRATION_BYTES - 1000 < len(bomb) <= MAX_CALIBRATION_BYTES
    started = time.perf_counter()
    with pytest.raises(RigError) as refused:
        parse_rig(bomb, flow_files[1])
    assert time.perf_counter() - started < 0.5  # 10 ms with libyaml, 150 ms with PyYAML's pure-Python reader
    assert refused.value.field == "left.a1" and refused.value.reason.startswith("holds a YAML alias (*name)")


@pytest.mark.parametrize(
    ("old", "new", "field", "reason"),
    [
        (
            "distortion_model: plumb_bob",
            "distortion_model: equidistant",
            "left.distortion_model",
            "'equidistant' is not",
        ),
        (
            "camera_name: left",
            "camera_name: left\ncamera_name: left",
            "left.camera_name",
            "`camera_name` is given twice",
        ),
        (
            "camera_name: left",
            "camera_name: left\nk: [1, 2]",
            "left.camera_matrix",
            "`k` and `camera_matrix` both give",
        ),
        ("rows: 3\n  cols: 3", "rows: 3\n  rows: 3\n  cols: 3", "left.camera_matrix", "`rows` is given twice"),
        ("rows: 3\n  cols: 3", "rows: 3\n   cols: 3", "left camera_info", "line 6, column 8: mapping values are not"),
        ("data: [400.0,", "data: [.nan,", "left.camera_matrix", "holds a number that is not finite"),
        ("data: [400.0,", "data: [true,", "left.camera_matrix", "expected a list of numbers [1, 2, ...], got True"),
        ("camera_name: left", "camera_name: &name left\nframe_id: *name", "left.frame_id", "holds a YAML alias"),
        ("camera_name: left", "camera_name: !!python/name:os.system", "left.camera_name", "could not determine a"),
        ("camera_name: left\n", "camera_name: left\n---\ncamera_name: left\n", "left camera_info", "2 YAML documents"),
        ("rows: 3\n  cols: 3", "rows: 3\n  cols: 3\n  dt: d", "left.camera_matrix", "has exactly rows, cols, data"),
    ],
)
def test_a_camera_info_that_is_not_one_is_refused_naming_the_entry(flow_files, old, new, field, reason):
    left = flow_files[0]
    assert old in left
    left = left.replace(old, new, 1)
    with pytest.raises(RigError) as refused:
        parse_rig(left, flow_files[1])
    assert refused.value.field == field and reason in refused.value.reason, str(refused.value)


def test_numbers_of_yaml_1_2_with_an_exponent_and_no_dot_are_numbers():
    entries = parse_entries("height: 240\nwidth: 320\nd: [1e-05, -2E+3, 5, 0.5]\n", "left camera_info", "left.")
    assert entries["image_width"] == 320.0 and entries["image_height"] == 240.0
    assert np.array_equal(entries["distortion_coefficients"], [1e-05, -2000.0, 5.0, 0.5])
