"""HTTP service for CREStereo++ stereo disparity: FastAPI app with dynamic CPU batching.

Run: `uvicorn service.app:create_app --factory`; configuration in `service/README.md`.
"""

import os

# The inference worker shares the CPU with the event loop and the decoding threads (and, in a
# container, with its CPU quota): OpenMP threads that spin-wait between parallel regions steal
# that time and, once the CPU is oversubscribed, slow inference down by an order of magnitude.
# Sleeping waits avoid it. OpenMP reads this once, when torch loads, hence here, before any
# import of torch; a value set in the environment wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
