"""HTTP service for CREStereo++ stereo disparity: FastAPI app with dynamic CPU batching.

Run: `python -m crestereo_pp.service` (uvicorn with its limits; the app is
`service.api.app.create_app`); configuration in `service/README.md`. The package answers four
questions, one subpackage each: HTTP (`api`), untrusted uploads (`uploads`), batching
(`batching`) and scale-out on Ray (`ray`).
"""

import os

# The inference thread shares the CPU with the event loop and the decoding threads (and, in a
# container, with its CPU quota): OpenMP threads that spin-wait between parallel regions steal
# that time and, once the CPU is oversubscribed, slow inference down by an order of magnitude.
# Sleeping waits avoid it. OpenMP reads this once, when torch loads, hence here, before any
# import of torch; a value set in the environment wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# oneDNN (torch's CPU convolutions: `full`, and lite at iterations without an OpenVINO graph) keeps
# up to 1024 primitives by default, a few per layer and image shape: under a stream of distinct
# sizes the process grew by 385 MiB over 48 shapes, still growing (the cache's entries pin freed
# heap around them); with 64 it grew by 75-106 MiB and levelled off, at the same speed. Read once,
# at its first primitive; a value set in the environment wins.
os.environ.setdefault("ONEDNN_PRIMITIVE_CACHE_CAPACITY", "64")

DEFAULT_MAX_IMAGE_PIXELS = 4_194_304
"""Default of `Settings.max_image_pixels` (CRESTEREO_MAX_IMAGE_PIXELS)."""

# The decoder's own cap, from the service's pixel limit: the file headers are checked before
# decoding, but OpenCV's decoders read the headers themselves (libtiff, for one, takes the first
# of two conflicting size tags), so this cap is what guarantees that no file expands beyond the
# limit. OpenCV reads the variable once, at its first decode, hence here; a value set wins.
os.environ.setdefault(
    "OPENCV_IO_MAX_IMAGE_PIXELS", os.environ.get("CRESTEREO_MAX_IMAGE_PIXELS", str(DEFAULT_MAX_IMAGE_PIXELS))
)
