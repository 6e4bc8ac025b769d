"""Suite-wide setup, run before any test module imports torch.

OpenMP threads that spin while waiting turn 10-50x slower when the cores are oversubscribed,
which the suite does on purpose (a pytest process beside uvicorn servers and trainers on two
cores). Passive waiting keeps every process at its normal speed; children inherit it.
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
