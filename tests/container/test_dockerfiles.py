"""The container files themselves: hadolint on both Dockerfiles, and a valid compose file."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

DOCKER = Path(__file__).resolve().parents[2] / "docker"
DOCKERFILES = [DOCKER / "Dockerfile", DOCKER / "base.Dockerfile"]


def _tool(name: str) -> str:
    """A tool from the test environment (its bin/ first), or skip (a failure under CI)."""
    path = shutil.which(name, path=os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")]))
    if path is None:
        reason = f"{name} is not installed"
        if os.environ.get("CI"):
            pytest.fail(reason)
        pytest.skip(reason)
    return path


@pytest.mark.parametrize("dockerfile", DOCKERFILES, ids=lambda p: p.name)
def test_hadolint_passes(dockerfile: Path) -> None:
    result = subprocess.run(
        [_tool("hadolint"), "--no-color", str(dockerfile)], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_compose_file_is_valid_and_limits_resources() -> None:
    result = subprocess.run(
        [_tool("docker-compose"), "--file", str(DOCKER / "compose.yaml"), "config"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    config = result.stdout
    for key in ("cpus:", "mem_limit:", "healthcheck:", "restart:", "published:"):
        assert key in config, f"{key} missing from the resolved compose file:\n{config}"


def test_compose_passes_every_service_setting() -> None:
    """compose.yaml passes each CRESTEREO_* setting of the service through, no more, no less."""
    settings = pytest.importorskip("crestereo_pp.service.settings")
    expected = {settings.ENV_PREFIX + name.upper() for name in settings.Settings.model_fields}
    compose = (DOCKER / "compose.yaml").read_text()
    passed = set(re.findall(r"^\s+- (CRESTEREO_\w+)\s*$", compose, flags=re.MULTILINE))
    assert passed == expected, f"add {expected - passed}, remove {passed - expected}"


def test_container_readme_lists_every_service_setting() -> None:
    settings = pytest.importorskip("crestereo_pp.service.settings")
    readme = (DOCKER / "README.md").read_text()
    missing = [
        settings.ENV_PREFIX + name.upper()
        for name in settings.Settings.model_fields
        if f"`{settings.ENV_PREFIX}{name.upper()}`" not in readme
    ]
    assert not missing, f"docker/README.md does not document {missing}"
