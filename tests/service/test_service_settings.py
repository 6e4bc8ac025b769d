"""Settings: from the environment, validated, each documented in the README with its default."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from pydantic import ValidationError

from crestereo_pp.service.settings import Settings
from crestereo_pp.service.uploads.budgets import largest_stream_image
from service_helpers import REPO


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


def test_streams_have_a_byte_budget_and_an_image_size_of_their_own():
    default = Settings.from_env({})
    assert (default.max_stream_bytes, default.max_stream_image_bytes) == (64 << 20, 16 << 20)
    assert default.max_upload_bytes == 192 << 20  # the request bodies' budget, apart
    # one message of a stream: the stream image size, or the largest file of the model's pixel limit where smaller
    largest = [
        largest_stream_image(default.pixel_limit(model), default.max_body_bytes, default.max_stream_image_bytes)
        for model in ("lite", "full")
    ]
    assert largest == [16 << 20, 9 << 20]  # full: 1,048,576 px x 8 B + 1 MiB
    custom = Settings.from_env({"CRESTEREO_MAX_STREAM_BYTES": "3000000", "CRESTEREO_MAX_STREAM_IMAGE_BYTES": "1000"})
    assert (custom.max_stream_bytes, custom.max_stream_image_bytes) == (3_000_000, 1000)


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
        {"CRESTEREO_MAX_STREAM_IMAGE_BYTES": "0"},
        {"CRESTEREO_MAX_STREAM_BYTES": "1000", "CRESTEREO_MAX_STREAM_IMAGE_BYTES": "501"},
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
