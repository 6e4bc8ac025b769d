"""The answer's depth edges put back where the image's colour edges are
(``InferenceOptions.refine_edges``).

The network's answer is smooth across depth edges: within a few pixels of one, a pixel's
disparity is a blur of the two sides' (the model card's "Edges and thin structures"). A joint
weighted median (as in classical stereo pipelines' refinement: Ma et al., "Constant time weighted
median filtering for stereo matching and beyond", ICCV 2013) gives each pixel near a depth edge
the weighted median of the disparities around it, weighted by how alike the left image's colours
are (CIE Lab) and how near: a pixel takes the disparity of the side whose colour it has. Each
answer is one of the neighbours' answers: nothing new is invented, and pixels away from depth
edges keep their answer. Host work, on the CPU.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

EDGE_GRADIENT_PX = 1.0
"""A depth edge: the answer changes by more than this many pixels of disparity per pixel
(Sobel, either direction)."""

EDGE_REACH_PX = 2
"""Pixels up to this far from a depth edge are refined."""

MEDIAN_RADIUS_PX = 6
MEDIAN_STEP_PX = 2
"""The median's neighbours: every MEDIAN_STEP_PX px up to MEDIAN_RADIUS_PX px away in x and y
(a 7x7 grid of 49, the pixel itself among them)."""

COLOUR_SIGMA = 10.0
"""The colour weight's width: exp(-|Lab difference|^2 / (2 sigma^2)), Lab in OpenCV's 8-bit
scale (L 0-255)."""

DISTANCE_SIGMA_PX = 6.0
"""The distance weight's width: exp(-distance^2 / (2 sigma^2)), px."""

EDGE_PIXELS_PER_CHUNK = 32_768
"""Edge pixels refined at a time: their neighbours' indices, values and weights take a few tens
of MB, whatever the image's size (an all-edge 1024x1024 answer at once took 1.9 GB)."""


def depth_edge_pixels(disparity: np.ndarray) -> np.ndarray:
    """HxW bool: the pixels of `disparity` (HxW float32, px) within EDGE_REACH_PX of a depth edge
    (EDGE_GRADIENT_PX)."""
    change = np.abs(cv2.Sobel(disparity, cv2.CV_32F, 1, 0, ksize=3)) + np.abs(
        cv2.Sobel(disparity, cv2.CV_32F, 0, 1, ksize=3)
    )
    edges = (change > 8.0 * EDGE_GRADIENT_PX).astype(np.uint8)  # a Sobel sums 8 steps of one px each
    reach = 2 * EDGE_REACH_PX + 1
    return cv2.dilate(edges, np.ones((reach, reach), np.uint8)) > 0


def refine_depth_edges(disparity: np.ndarray, left: np.ndarray) -> np.ndarray:
    """`disparity` (HxW float32, px, the answer for the left view) with each pixel near a depth
    edge (``depth_edge_pixels``) replaced by the weighted median of its neighbours' disparities
    (see the module; MEDIAN_RADIUS_PX, COLOUR_SIGMA, DISTANCE_SIGMA_PX). `left`: the left image,
    HxWx3 uint8 RGB (``sgbm.host_rgb8``). Returns a new HxW float32 array; the answer unchanged
    where it holds a NaN or an infinity. The edge pixels go EDGE_PIXELS_PER_CHUNK at a time, so
    that the memory it takes does not grow with the image."""
    if not np.isfinite(disparity).all():
        return disparity
    rows, cols = np.nonzero(depth_edge_pixels(disparity))
    r = MEDIAN_RADIUS_PX
    width = disparity.shape[1] + 2 * r  # the maps edge-padded by r, flattened
    padded = torch.from_numpy(cv2.copyMakeBorder(disparity, r, r, r, r, cv2.BORDER_REPLICATE).ravel())
    lab = cv2.copyMakeBorder(cv2.cvtColor(left, cv2.COLOR_RGB2LAB), r, r, r, r, cv2.BORDER_REPLICATE)
    colour = torch.from_numpy(lab.reshape(-1, 3).T.astype(np.float32))  # (3, pixels)
    dy, dx = np.mgrid[-r : r + 1 : MEDIAN_STEP_PX, -r : r + 1 : MEDIAN_STEP_PX]
    offsets = torch.from_numpy((dy * width + dx).ravel())
    distance = torch.from_numpy((-(dy * dy + dx * dx) / (2 * DISTANCE_SIGMA_PX**2)).ravel().astype(np.float32))
    centres = torch.from_numpy((rows + r) * width + cols + r)
    refined = disparity.copy()
    for start in range(0, len(centres), EDGE_PIXELS_PER_CHUNK):
        centre = centres[start : start + EDGE_PIXELS_PER_CHUNK]
        neighbours = centre[:, None] + offsets[None, :]  # (n, 49) indices into the padded maps
        log_weight = distance.expand(len(centre), -1).clone()
        for channel in colour:
            log_weight -= (channel[neighbours] - channel[centre][:, None]).square_() / (2 * COLOUR_SIGMA**2)
        values, order = torch.sort(padded[neighbours], dim=1)
        cumulative = torch.cumsum(torch.gather(log_weight.exp_(), 1, order), dim=1)
        median = (cumulative < 0.5 * cumulative[:, -1:]).sum(dim=1, keepdim=True)
        chunk = slice(start, start + len(centre))
        refined[rows[chunk], cols[chunk]] = torch.gather(values, 1, median)[:, 0].numpy()
    return refined
