"""`python3 bench/gpu_check ARGS` runs the GPU check (`orchestrator.main`); so does `python3 -m
gpu_check ARGS` with bench/ on the path.

Run as a folder, Python puts bench/gpu_check/ itself first on sys.path, where neither this package
nor its sibling scripts (train_speed.py, timing.py, service_load.py) can be imported. So that run
replaces itself (os.execve, the same process) with `python3 -P -m gpu_check ARGS`, bench/ added to
PYTHONPATH; the stages' processes, started the same way, inherit it. No sys.path is edited, and -P
keeps the working directory off it (as running a script did), so that only the package, bench/ and
the link tree of the project are importable.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

if __package__:  # python3 -m gpu_check
    from .orchestrator import main

    sys.exit(main())
else:  # python3 bench/gpu_check
    bench = str(Path(__file__).resolve().parents[1])
    environment = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (bench, os.environ.get("PYTHONPATH"))))}
    os.execve(sys.executable, [sys.executable, "-P", "-m", "gpu_check", *sys.argv[1:]], environment)
