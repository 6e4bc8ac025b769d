"""`python bench/mixed_load ARGS` runs the mixed-load benchmark (`cli.main`); so does `python -m
mixed_load ARGS` with bench/ on the path.

As bench/gpu_check/__main__.py does: run as a folder, Python puts bench/mixed_load/ itself first on
sys.path, where neither this package nor its sibling script service_load.py can be imported. So
that run replaces itself (os.execve, the same process) with `python -P -m mixed_load ARGS`, bench/
added to PYTHONPATH, which the sampling process (multiprocessing, spawned) inherits. No sys.path is
edited, and -P keeps the working directory off it, as running a script did.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

if __package__:  # python -m mixed_load
    from .cli import main

    sys.exit(main())
else:  # python bench/mixed_load
    bench = str(Path(__file__).resolve().parents[1])
    environment = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (bench, os.environ.get("PYTHONPATH"))))}
    os.execve(sys.executable, [sys.executable, "-P", "-m", "mixed_load", *sys.argv[1:]], environment)
