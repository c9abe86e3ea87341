"""Pinhole helpers: back-projection round-trips through the projection."""

import numpy as np
import pytest

from splatsearch.camera import pixels_to_world


def _look(yaw: float, t) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])  # a turn about the camera's y (down) axis
    V = np.eye(4)
    V[:3, :3] = R
    V[:3, 3] = t
    return V


def test_pixels_to_world_inverts_the_projection():
    K = np.array([[300.0, 0, 160], [0, 310.0, 120], [0, 0, 1]])
    V = _look(0.4, [0.3, -1.2, 2.0])
    rows, cols = np.mgrid[0:240:7, 0:320:9]
    z = np.linspace(0.5, 4.0, rows.size).reshape(rows.shape)
    pw = pixels_to_world(cols, rows, z, V, K)
    assert pw.shape == rows.shape + (3,) and pw.dtype == np.float64
    pc = pw @ V[:3, :3].T + V[:3, 3]
    np.testing.assert_allclose(pc[..., 2], z, atol=1e-9)
    np.testing.assert_allclose(K[0, 0] * pc[..., 0] / pc[..., 2] + K[0, 2], cols + 0.5, atol=1e-9)
    np.testing.assert_allclose(K[1, 1] * pc[..., 1] / pc[..., 2] + K[1, 2], rows + 0.5, atol=1e-9)
    # zero depth is the camera centre
    centre = -V[:3, :3].T @ V[:3, 3]
    np.testing.assert_allclose(pixels_to_world(5, 7, 0.0, V, K), centre, atol=1e-12)
    with pytest.raises(ValueError):
        pixels_to_world(cols, rows, z, V[:3], K)
