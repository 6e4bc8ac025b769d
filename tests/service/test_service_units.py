"""Settings, CPU quota, image headers and decoding, result encodings."""

from __future__ import annotations

import os
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from pydantic import ValidationError

from service.cpu import cgroup_cpu_quota, usable_cpus
from service.encoding import encode_preview
from service.images import ImageError, decode_rgb, read_header
from service.settings import Settings
from service_helpers import REPO, encode, stereo_pair
from stereo_data.visualize import BAR_HEIGHT, PREVIEW_GAP, scale_range

# --- settings ----------------------------------------------------------------------------------


def test_settings_default_to_serving_both_models_without_an_api_key():
    settings = Settings.from_env({})
    assert settings.models == ("lite", "full")
    assert settings.api_key is None and settings.weights == {}


def test_settings_come_from_crestereo_environment_variables():
    settings = Settings.from_env(
        {
            "CRESTEREO_MODELS": "lite",
            "CRESTEREO_MAX_BATCH_SIZE": "4",
            "CRESTEREO_WEIGHTS": "lite=/w/lite.pt, full=/w/full.pt",
            "CRESTEREO_API_KEY": "k",
            "CRESTEREO_MAX_WAIT_MS": "2.5",
            "OTHER_MAX_BATCH_SIZE": "99",
            "CRESTEREO_PRECISION": "bf16",
        }
    )
    assert settings.models == ("lite",) and settings.max_batch_size == 4
    assert settings.weights == {"lite": Path("/w/lite.pt"), "full": Path("/w/full.pt")}
    assert settings.api_key == "k" and settings.max_wait_ms == 2.5 and settings.precision == "bf16"


def test_each_model_has_its_pixel_limit_under_the_global_one():
    default = Settings.from_env({})
    assert (default.pixel_limit("lite"), default.pixel_limit("full")) == (4_194_304, 1_048_576)
    custom = Settings.from_env(
        {"CRESTEREO_MODEL_MAX_PIXELS": "lite=2000000, full=9000000", "CRESTEREO_MAX_IMAGE_PIXELS": "3000000"}
    )
    assert (custom.pixel_limit("lite"), custom.pixel_limit("full")) == (2_000_000, 3_000_000)


@pytest.mark.parametrize(
    "environ",
    [
        {"CRESTEREO_MODELS": "lite,huge"},
        {"CRESTEREO_MAX_BATCH_SIZE": "0"},
        {"CRESTEREO_WEIGHTS": "lite"},
        {"CRESTEREO_MODELS": ""},
        {"CRESTEREO_MODEL_MAX_PIXELS": "full=many"},
        {"CRESTEREO_MODEL_MAX_PIXELS": "huge=5"},
        {"CRESTEREO_PRECISION": "fp16"},
    ],
)
def test_invalid_settings_stop_the_service_from_starting(environ):
    with pytest.raises(ValidationError):
        Settings.from_env(environ)


def test_readme_documents_every_setting_with_its_default():
    readme = (REPO / "service" / "README.md").read_text()
    rows = dict(re.findall(r"^\| `(CRESTEREO_[A-Z_]+)` \| ([^|]+) \|", readme, re.MULTILINE))
    defaults = Settings()
    expected = {
        "CRESTEREO_" + name.upper(): documented_default(getattr(defaults, name)) for name in Settings.model_fields
    }
    assert {name: cell.strip() for name, cell in rows.items()} == expected


def documented_default(value: object) -> str:
    if value is None or value == {}:
        return "(none)"
    if isinstance(value, tuple):
        return "`" + ",".join(value) + "`"
    if isinstance(value, dict):
        return "`" + ",".join(f"{key}={item}" for key, item in value.items()) + "`"
    if isinstance(value, float) and value.is_integer():
        return f"`{int(value)}`"
    return f"`{value}`"


# --- CPU quota ---------------------------------------------------------------------------------


def test_cpu_quota_is_read_from_cgroup_v2(tmp_path):
    (tmp_path / "cpu.max").write_text("250000 100000\n")
    assert cgroup_cpu_quota(tmp_path) == 2.5
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert cgroup_cpu_quota(tmp_path) is None


def test_cpu_quota_is_read_from_cgroup_v1(tmp_path):
    (tmp_path / "cpu").mkdir()
    (tmp_path / "cpu" / "cpu.cfs_period_us").write_text("100000\n")
    (tmp_path / "cpu" / "cpu.cfs_quota_us").write_text("150000\n")
    assert cgroup_cpu_quota(tmp_path) == 1.5
    (tmp_path / "cpu" / "cpu.cfs_quota_us").write_text("-1\n")
    assert cgroup_cpu_quota(tmp_path) is None


def test_usable_cpus_round_the_quota_down_and_fall_back_to_the_cores(tmp_path):
    cores = len(os.sched_getaffinity(0))
    assert usable_cpus(tmp_path) == cores  # no cgroup files: the cores we may run on
    (tmp_path / "cpu.max").write_text("50000 100000\n")
    assert usable_cpus(tmp_path) == 1
    (tmp_path / "cpu.max").write_text(f"{(cores + 8) * 100000} 100000\n")
    assert usable_cpus(tmp_path) == cores


# --- images ------------------------------------------------------------------------------------


@pytest.mark.parametrize("ext", [".png", ".jpg", ".bmp", ".tiff"])
def test_header_gives_format_and_size_of_every_supported_format(ext):
    left, _ = stereo_pair(40, 72)
    header = read_header(encode(left, ext))
    assert (header.width, header.height) == (72, 40)
    assert header.format == {".png": "PNG", ".jpg": "JPEG", ".bmp": "BMP", ".tiff": "TIFF"}[ext]


@pytest.mark.parametrize(
    ("image", "expected"),
    [
        (np.full((40, 72), 200, np.uint8), 200),  # grayscale, 8-bit
        (np.full((40, 72, 3), 65535, np.uint16), 255),  # colour, 16-bit
        (np.dstack([np.full((40, 72, 3), 10, np.uint8), np.zeros((40, 72), np.uint8)]), 10),  # alpha
    ],
)
def test_decoding_gives_8_bit_rgb(image, expected):
    data = cv2.imencode(".png", image)[1].tobytes()
    rgb = decode_rgb(data, read_header(data))
    assert rgb.shape == (40, 72, 3) and rgb.dtype == np.uint8
    assert (rgb == expected).all()


def test_decoding_keeps_rgb_channel_order():
    image = np.zeros((40, 72, 3), np.uint8)
    image[..., 0] = 255  # red
    data = encode(image)
    assert decode_rgb(data, read_header(data))[0, 0].tolist() == [255, 0, 0]


def test_unknown_and_truncated_files_are_told_apart():
    with pytest.raises(ImageError) as unknown:
        read_header(b"GIF89a....")
    with pytest.raises(ImageError) as truncated:
        read_header(b"\x89PNG\r\n\x1a\n\x00\x00")
    assert unknown.value.unsupported and not truncated.value.unsupported


# --- encodings ---------------------------------------------------------------------------------


def test_preview_puts_disparity_left_of_uncertainty_with_color_bars_on_their_scales():
    disparity = np.tile(np.linspace(12.0, 53.0, 64, dtype=np.float32), (40, 1))  # a Middlebury range
    uncertainty = np.tile(np.linspace(0.0, 1.0, 64, dtype=np.float32), (40, 1))
    png = encode_preview(disparity, uncertainty, scale_range(disparity))
    preview = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]
    assert preview.shape == (40 + BAR_HEIGHT, 128 + PREVIEW_GAP, 3)
    turbo = cv2.applyColorMap(np.array([[0, 255]], np.uint8), cv2.COLORMAP_TURBO)[0, :, ::-1]
    # the map's own range spans the whole colour map (not the bottom quarter of a fixed 0-192)
    assert np.abs(preview[0, 0].astype(int) - turbo[0]).max() <= 40
    assert np.abs(preview[0, 63].astype(int) - turbo[1]).max() <= 40
    inferno = cv2.applyColorMap(np.array([[255]], np.uint8), cv2.COLORMAP_INFERNO)[0, 0, ::-1]
    assert (preview[0, 127 + PREVIEW_GAP] == inferno).all()
    assert (preview[:, 64 : 64 + PREVIEW_GAP] == 255).all()  # the two bars' end labels stay apart
    assert (preview[40:] == 255).any() and (preview[40:] < 128).any()  # bars: white with dark text


def test_a_fixed_color_scale_is_honoured_and_a_reversed_one_refused():
    disparity = np.full((8, 8), 30.0, np.float32)
    assert scale_range(disparity, 0.0, 192.0) == (0.0, 192.0)
    low, high = scale_range(disparity)
    assert high > low  # a constant map still gets a scale
    with pytest.raises(ValueError, match="above"):
        scale_range(disparity, 50.0, 10.0)
