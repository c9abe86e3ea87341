"""Pinhole camera helpers in the project's conventions.

OpenCV camera frame (x right, y down, z forward); ``viewmat`` is the 4x4 world-to-camera
transform; ``K`` the 3x3 intrinsics in pixels; pixel (col, row) has its centre at (col + 0.5,
row + 0.5); depth is the z distance in metres.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike


def pixels_to_world(cols: ArrayLike, rows: ArrayLike, depth: ArrayLike, viewmat: ArrayLike,
                    K: ArrayLike) -> np.ndarray:
    """World points (..., 3) float64, metres, of pixels at integer ``cols`` / ``rows`` (any
    broadcastable shapes) with z-depth ``depth`` (metres) seen by the camera ``viewmat`` (4, 4)
    world-to-camera with intrinsics ``K`` (3, 3). A depth of 0 gives the camera centre: callers
    mask invalid pixels themselves."""
    K = np.asarray(K, np.float64)
    viewmat = np.asarray(viewmat, np.float64)
    if viewmat.shape != (4, 4) or K.shape != (3, 3):
        raise ValueError(f"viewmat must be (4, 4) and K (3, 3), got {viewmat.shape}, {K.shape}")
    z = np.asarray(depth, np.float64)
    x = (np.asarray(cols, np.float64) + 0.5 - K[0, 2]) / K[0, 0] * z
    y = (np.asarray(rows, np.float64) + 0.5 - K[1, 2]) / K[1, 1] * z
    cam = np.stack(np.broadcast_arrays(x, y, z), -1)
    c2w = np.linalg.inv(viewmat)
    return cam @ c2w[:3, :3].T + c2w[:3, 3]
