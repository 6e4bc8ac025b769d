"""The strip along the left image's left edge whose matches fall outside the right image, raised
towards the surface beside it (part of ``InferenceOptions.refine_edges``).

A pixel of the left image at x with disparity d is seen by the right camera at x - d; where that
is left of the right image (x - d < 0), nothing in the pair matches it, and the network's answer
there is an extrapolation from the pixels beside it. Where the strip is wide that extrapolation
tends to fall short: on procedural scenes, where every pixel's truth is known, and on the real
pairs with the widest strips, the network's answer in the strip lies below the disparity where the
strip ends (a surface's disparity carries on into the strip; the matches the network can find
there are of smaller disparities), though on some pairs it overshoots. Each row's strip (the
pixels left of the first one whose match lies inside the right image) is raised towards the
answer at the strip's end, by at most STRIP_RAISE_PX, and by less where the left image's colour
differs from the colour where the strip ends (another surface): never lowered, and a nearer
object that the network saw in the strip keeps its answer but for a few pixels. Host work, on the
CPU.
"""

from __future__ import annotations

import cv2
import numpy as np

STRIP_RAISE_PX = 4.0
"""The most a strip pixel's disparity is raised, px. Of 2, 3, 4, 6, 8 and 16 px and no bound, the
larger bounds got a few more pixels within 2 px and a larger mean error (no bound: plain
procedural scenes' 6.09 -> 6.30 px); 4 px is the largest that kept the mean error within 0.003 px
of the lowest on every procedural set (the model card, "The left edge's strip raised")."""

STRIP_COLOUR_SIGMA = 20.0
"""The raise is scaled by exp(-|Lab difference|^2 / (2 sigma^2)) between a strip pixel's colour and
the colour where its row's strip ends (Lab in OpenCV's 8-bit scale): without it the mean error
rose on six of eight kinds of procedural scene; with sigma 20 on three, by under 0.025 px."""


def strip_ends(disparity: np.ndarray) -> np.ndarray:
    """(H,) int: per row of `disparity` (HxW, px, the answer for the left view), the first column
    whose match lies inside the right image (x - d >= 0): the row's strip is the columns left of
    it. 0 (no strip) for a row in which no pixel's match lies inside."""
    columns = np.arange(disparity.shape[1], dtype=np.float32)
    inside = columns[None, :] - disparity >= 0  # False where the answer is NaN
    return np.where(inside.any(axis=1), inside.argmax(axis=1), 0)


def raise_border_strip(disparity: np.ndarray, left: np.ndarray) -> np.ndarray:
    """`disparity` (HxW float32, px, the answer for the left view) with each row's strip
    (``strip_ends``) raised towards the answer at its end, by at most STRIP_RAISE_PX, scaled by how
    alike the pixel's colour in `left` (HxWx3 uint8 RGB, ``sgbm.host_rgb8``) is to the colour at
    the strip's end (STRIP_COLOUR_SIGMA). Pixels right of the strip, and strip pixels at or above
    the answer at its end, keep theirs (a NaN stays a NaN). Returns a new HxW float32 array."""
    ends = strip_ends(disparity)
    reach = int(ends.max())  # the strips lie in the columns left of this one
    rows = np.arange(disparity.shape[0])
    strips = disparity[:, :reach]
    lab = cv2.cvtColor(np.ascontiguousarray(left[:, : reach + 1]), cv2.COLOR_RGB2LAB).astype(np.float32)
    beside = disparity[rows, ends][:, None]  # (H, 1): the answer where each strip ends
    difference = lab[:, :reach] - lab[rows, ends][:, None, :]
    likeness = np.exp(-np.square(difference).sum(axis=-1) / (2 * STRIP_COLOUR_SIGMA**2))
    raised = strips + np.clip(beside - strips, 0.0, STRIP_RAISE_PX) * likeness
    refined = disparity.astype(np.float32, copy=True)
    in_strip = np.arange(reach)[None, :] < ends[:, None]
    refined[:, :reach] = np.where(in_strip, raised, strips)
    return refined
