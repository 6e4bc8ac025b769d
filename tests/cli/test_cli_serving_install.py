"""The CLI in the environment `make serve` builds: the package without extras; and what a plain
`pip install` of the project puts into site-packages.

The test environment has every extra, so a module that imports a package only an extra brings
(scipy, through scikit-image) passes every other test; here the CLI runs in a fresh virtual
environment holding the runtime dependencies alone.

Building it for real would unpack torch and the rest (about 1.4 GB) for a minute or more. Instead
the fresh environment sees exactly the distributions that `pip install -e .` would put there, those
of the project's runtime requirements and theirs (read from the metadata of the test environment,
where they are installed at the versions pip chose), through links to their files in a folder on
its path; then `pip install -e .` installs the project itself as the Makefile does, and finds
every requirement met. Nothing else of the test environment is visible: a dependency that no
requirement declares is missing there, as after `make serve`.
"""

import json
import os
import re
import subprocess
import sys
from importlib.metadata import Distribution, distribution
from pathlib import Path

import pytest
from packaging.requirements import Requirement

from crestereo_pp.cli.main import COMMANDS

REPO = Path(__file__).resolve().parents[2]
PROJECT = "crestereo-pp"


def runtime_distributions(project: str = PROJECT) -> dict[str, Distribution]:
    """The installed distributions that `project` needs without extras, by normalised name
    (the project's own excluded)."""
    found: dict[str, Distribution] = {}
    wanted = [Requirement(spec) for spec in distribution(project).requires or []]
    while wanted:
        requirement = wanted.pop()
        name = re.sub(r"[-_.]+", "-", requirement.name).lower()
        if name in found or (requirement.marker is not None and not requirement.marker.evaluate({"extra": ""})):
            continue
        found[name] = distribution(requirement.name)
        wanted += [Requirement(spec) for spec in found[name].requires or []]
    return found


def link_distributions(distributions: dict[str, Distribution], folder: Path) -> None:
    """Links in `folder` to every file the distributions installed, at the same relative paths: a
    namespace such as google/, shared with distributions of the extras, holds only theirs."""
    for dist in distributions.values():
        for file in dist.files or []:
            link = folder / file
            if file.parts[0] == ".." or link.exists():  # a script in bin/, or a file two of them list
                continue
            link.parent.mkdir(parents=True, exist_ok=True)
            link.symlink_to(Path(str(dist.locate_file(file))))


def fresh_environment(root: Path) -> Path:
    """A new virtual environment in root/venv that sees the runtime dependencies (through a .pth
    file naming root/runtime, outside its site-packages); returns its site-packages."""
    subprocess.run([sys.executable, "-m", "venv", root / "venv"], check=True)
    link_distributions(runtime_distributions(), root / "runtime")
    purelib = subprocess.run(
        [root / "venv" / "bin" / "python", "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    Path(purelib, "runtime-dependencies.pth").write_text(f"{root / 'runtime'}\n")
    return Path(purelib)


def pip_install(bin_dir: Path, *arguments: str | Path) -> None:
    installed = subprocess.run(
        [bin_dir / "python", "-m", "pip", "install", "--quiet", "--disable-pip-version-check", *arguments],
        capture_output=True,
        text=True,
        check=False,
    )
    assert installed.returncode == 0, installed.stderr


@pytest.fixture(scope="module")
def serving_install(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A fresh virtual environment as `make serve` leaves it; returns its bin/ folder."""
    root = tmp_path_factory.mktemp("serving-install")
    fresh_environment(root)
    pip_install(root / "venv" / "bin", "-e", REPO)
    return root / "venv" / "bin"


def readme_python_example() -> str:
    """The first Python block of the README's "Python" section."""
    section = (REPO / "README.md").read_text().split("\n### Python\n", 1)[1]
    return section.split("```python\n", 1)[1].split("```", 1)[0]


def run_cli(bin_dir: Path, *arguments: str, **environment: str) -> subprocess.CompletedProcess[str]:
    environ = {key: value for key, value in os.environ.items() if key != "CRESTEREO_BACKEND"}  # auto
    return subprocess.run(
        [bin_dir / "crestereo-pp", *arguments],
        capture_output=True,
        text=True,
        check=False,
        env={**environ, **environment},
    )


@pytest.mark.slow
def test_every_command_shows_its_help_in_the_serving_install(serving_install):
    for arguments in (["--help"], *([name, "--help"] for name in COMMANDS)):
        done = run_cli(serving_install, *arguments)
        assert done.returncode == 0, (arguments, done.stderr)


@pytest.mark.slow
def test_predict_computes_a_real_pair_on_torch_there_without_waiting_for_an_export(
    serving_install, small_stereo_dev, tmp_path
):
    pair = next(small_stereo_dev.iterdir())
    cache = tmp_path / "cache"
    output = tmp_path / "disparity.pfm"
    done = run_cli(
        serving_install,
        "predict",
        str(pair / "left.png"),
        str(pair / "right.png"),
        "-o",
        str(output),
        CRESTEREO_CACHE_DIR=str(cache),
    )
    assert done.returncode == 0, done.stderr
    assert output.is_file() and "computing on torch" in done.stderr
    assert [path for path in cache.rglob("*") if path.is_file()] == []  # no export was started


@pytest.mark.slow
def test_calibrate_says_it_needs_the_train_extra_there(serving_install, tmp_path):
    done = run_cli(serving_install, "calibrate", str(tmp_path / "weights.pt"))
    assert done.returncode != 0 and "pip install 'crestereo-pp[train]'" in done.stderr


@pytest.mark.slow
def test_a_plain_install_adds_only_crestereo_pp_and_the_readme_python_example_runs_there(
    small_stereo_dev, tmp_path_factory
):
    root = tmp_path_factory.mktemp("plain-install")
    site_packages = fresh_environment(root)
    before = {path.name for path in site_packages.iterdir()}
    pip_install(root / "venv" / "bin", "--no-deps", REPO)  # a wheel, as from a package index
    added = {path.name for path in site_packages.iterdir()} - before - {"__pycache__"}
    assert added == {"crestereo_pp", "crestereo_pp-0.1.0.dist-info"}, added
    assert (site_packages / "crestereo_pp" / "model" / "weights" / "lite.pt").is_file()

    # The example reads left.png and right.png from the folder it runs in: a real pair, copied there.
    work = root / "work"
    work.mkdir()
    pair = next(small_stereo_dev.iterdir())
    for name in ("left.png", "right.png"):
        (work / name).write_bytes((pair / name).read_bytes())
    script = readme_python_example() + (
        "\nimport json, numpy as np, crestereo_pp\n"
        "print(json.dumps({'package': crestereo_pp.__file__, 'shape': list(disparity.shape),\n"
        "    'pair': list(left.shape[:2]), 'finite': float(np.isfinite(disparity).mean()),\n"
        "    'uncertainty': [float(uncertainty.min()), float(uncertainty.max())]}))\n"
    )
    environ = {key: value for key, value in os.environ.items() if key not in ("PYTHONPATH", "CRESTEREO_BACKEND")}
    ran = subprocess.run(
        [root / "venv" / "bin" / "python", "-c", script],
        cwd=work,
        capture_output=True,
        text=True,
        check=False,
        env={**environ, "CRESTEREO_CACHE_DIR": str(root / "cache")},
        timeout=300,
    )
    assert ran.returncode == 0, ran.stderr
    printed = json.loads(ran.stdout.strip().splitlines()[-1])
    assert printed["package"] == str(site_packages / "crestereo_pp" / "__init__.py")  # not this checkout
    assert printed["shape"] == printed["pair"] and printed["finite"] == 1.0
    assert 0.0 <= printed["uncertainty"][0] <= printed["uncertainty"][1] <= 1.0
