"""The installed layout without installing: a folder `DEST/crestereo_pp/` of symbolic links to this
tree's folders, as pyproject.toml's `package-dir` maps them (`crestereo_pp/model` -> `model/`, ...).

    python3 tools/package_tree.py DEST      # then PYTHONPATH=DEST python3 -m crestereo_pp.service

For what cannot use the editable install's import hook: mypy (`make lint`) and a machine with its own
Python and no package index (the GPU check, `make gpu`). Edits in the tree are seen at once.
"""

from __future__ import annotations

import argparse
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def package_dirs(pyproject: Path = ROOT / "pyproject.toml") -> dict[str, Path]:
    """Top-level subpackage name ("crestereo_pp.model") -> its folder in this tree, from `package-dir`."""
    mapping: dict[str, str] = tomllib.loads(pyproject.read_text())["tool"]["setuptools"]["package-dir"]
    return {name: ROOT / folder for name, folder in mapping.items()}


def write_tree(dest: Path) -> Path:
    """Make (or refresh) `dest/crestereo_pp/`: its __init__.py and one link per subpackage; returns `dest`."""
    package = dest / "crestereo_pp"
    package.mkdir(parents=True, exist_ok=True)
    for name, folder in package_dirs().items():
        if name == "crestereo_pp":
            link, target = package / "__init__.py", folder / "__init__.py"
        else:
            link, target = package / name.removeprefix("crestereo_pp."), folder
        if link.is_symlink() or link.exists():
            link.unlink()
        link.symlink_to(target)
    return dest


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dest", type=Path, help="folder to hold crestereo_pp/ (made if missing)")
    print(write_tree(parser.parse_args().dest.resolve()))


if __name__ == "__main__":
    main()
