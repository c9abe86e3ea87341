"""Depth clean-up for real RGB-D sensors (Kinect, RealSense) before mapping.

Structured-light and stereo depth is missing at object boundaries, on dark or shiny surfaces and
beyond a few metres, and "flying pixels" sit between the two surfaces of a depth edge. The mapper
uses :func:`clean_depth` for its losses (trusted depth only) and :func:`fill_depth_holes` for
densification, so pixels without depth still get Gaussians that the colour loss can fit instead
of staying empty (black) in every render.
"""

from __future__ import annotations

import cv2
import numpy as np


def clean_depth(depth: np.ndarray, min_depth: float = 0.0, max_depth: float = float("inf"),
                edge_rel: float = 0.0) -> np.ndarray:
    """Depth (H, W) metres with untrusted pixels set to 0 (invalid).

    Pixels outside [``min_depth``, ``max_depth``] m are dropped; with ``edge_rel`` > 0 so are
    pixels whose 3x3 neighbourhood spans a depth jump larger than ``edge_rel`` times their depth
    (both sides of a depth edge, where the sensor mixes foreground and background).
    """
    d = np.asarray(depth, np.float32).copy()
    d[~np.isfinite(d)] = 0.0
    d[(d < min_depth) | (d > max_depth)] = 0.0
    if edge_rel > 0:
        valid = d > 0
        big = np.where(valid, d, 0.0).astype(np.float32)
        small = np.where(valid, d, np.float32(1e6)).astype(np.float32)
        k = np.ones((3, 3), np.uint8)
        hi = cv2.dilate(big, k)
        lo = cv2.erode(small, k)
        d[valid & ((hi - lo) > edge_rel * d)] = 0.0
    return d


def fill_depth_holes(depth: np.ndarray, max_iters: int = 64) -> np.ndarray:
    """Depth (H, W) with every invalid pixel given the depth of the farthest valid pixel nearby.

    Holes are filled by repeated 3x3 max-filtering (about one pixel per pass, ``max_iters``
    passes at most): taking the farthest neighbour puts a hole at an object boundary on the
    background surface behind it, where the missing Kinect pixels usually are. Pixels beyond
    reach stay 0.
    """
    d = np.asarray(depth, np.float32).copy()
    hole = d <= 0
    if not hole.any() or hole.all():
        return d
    k = np.ones((3, 3), np.uint8)
    for _ in range(max_iters):
        grown = cv2.dilate(d, k)
        upd = hole & (d <= 0) & (grown > 0)
        if not upd.any():
            break
        d[upd] = grown[upd]
        if not (d <= 0).any():
            break
    return d
