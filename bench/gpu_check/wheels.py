"""The service stage's packages on a machine without a package index: wheels carried with the tree,
installed with pip --no-index into a folder of their own."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any


def install_wheels(wheels: Path, target: Path, log: Any) -> str:
    """pip-install the wheels of `wheels` (no index, no dependencies) into `target`."""
    files = sorted(str(p) for p in wheels.glob("*.whl"))
    log.write(f"installing {len(files)} wheels from {wheels} into {target}\n")
    log.flush()
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "-q",
            "--no-index",
            "--no-deps",
            "--no-compile",
            "--target",
            str(target),
            *files,
        ],
        stdout=log,
        stderr=subprocess.STDOUT,
        check=False,
    )
    return str(target)
