"""Where the shared real stereo pairs with ground truth are (tests read them, never train on them).

$STEREO_DEV if set, else `shared/data/stereo-dev` beside the repository, else the workplace's
`/work/shared/data/stereo-dev` (so that a clone elsewhere, as CI makes, still finds them). Tests
that need the pairs skip, saying so, when none of these exists.
"""

import os
from pathlib import Path

_BESIDE_REPOSITORY = Path(__file__).resolve().parents[2] / "shared" / "data" / "stereo-dev"
_CANDIDATES = [os.environ.get("STEREO_DEV"), _BESIDE_REPOSITORY, "/work/shared/data/stereo-dev"]

STEREO_DEV: Path = next((Path(p) for p in _CANDIDATES if p and Path(p).is_dir()), _BESIDE_REPOSITORY)

SMALL_STEREO_DEV_PAIR = "middlebury2001_tsukuba"  # 384x288, the smallest pair: keeps CPU tests fast
