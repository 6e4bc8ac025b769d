"""The strip along the left image's left edge whose matches fall outside the right image, raised
towards the surface beside it (part of ``InferenceOptions.refine_edges``).

A pixel of the left image at x with disparity d is seen by the right camera at x - d; where that
is left of the right image (x - d < 0), nothing in the pair matches it, and the network's answer
there is an extrapolation from the pixels beside it. That extrapolation falls short: on procedural
scenes, where every pixel's truth is known, and on most real pairs, the network's answer in the
strip lies below the disparity where the strip ends (a surface's disparity carries on into the
strip; the matches the network can find there are of smaller disparities). Each row's strip (the
pixels left of the first one whose match lies inside the right image) is raised towards the
answer at the strip's end, by at most STRIP_RAISE_PX: never lowered, and a nearer object that
the network saw in the strip keeps its answer but for a few pixels. Host work, on the CPU.
"""

from __future__ import annotations

import numpy as np

STRIP_RAISE_PX = 4.0
"""The most a strip pixel's disparity is raised, px. The fewest errors over 2 px of 2, 3, 4, 6, 8
and 16 px and no bound on procedural validation scenes and the dev pairs alike, with the mean
error lowest at 3-6 px (the model card, "The left edge's strip raised")."""


def strip_ends(disparity: np.ndarray) -> np.ndarray:
    """(H,) int: per row of `disparity` (HxW, px, the answer for the left view), the first column
    whose match lies inside the right image (x - d >= 0): the row's strip is the columns left of
    it. 0 (no strip) for a row in which no pixel's match lies inside."""
    columns = np.arange(disparity.shape[1], dtype=np.float32)
    inside = columns[None, :] - disparity >= 0  # False where the answer is NaN
    return np.where(inside.any(axis=1), inside.argmax(axis=1), 0)


def raise_border_strip(disparity: np.ndarray) -> np.ndarray:
    """`disparity` (HxW float32, px, the answer for the left view) with each row's strip
    (``strip_ends``) raised towards the answer at its end, by at most STRIP_RAISE_PX; pixels right
    of the strip, and strip pixels at or above the answer at its end, keep theirs (a NaN stays a
    NaN). Returns a new HxW float32 array."""
    ends = strip_ends(disparity)
    beside = disparity[np.arange(disparity.shape[0]), ends][:, None]  # (H, 1): the answer where each strip ends
    raised = np.minimum(np.maximum(disparity, beside), disparity + np.float32(STRIP_RAISE_PX))
    strip = np.arange(disparity.shape[1])[None, :] < ends[:, None]
    return np.where(strip, raised, disparity).astype(np.float32)
