"""Planar (ground-robot) tracking: the pose update keeps height, roll and pitch."""

import jax.numpy as jnp
import numpy as np
import pytest

from splatsearch.slam import perturb_viewmat, planar_basis, pose_distance, project_planar, track
from splatsearch.sim.env import camera_viewmat


def _centre(vm):
    vm = np.asarray(vm, np.float64)
    return -vm[:3, :3].T @ vm[:3, 3]


def test_planar_basis_keeps_height_and_tilt():
    vm = camera_viewmat(1.0, 2.0, 0.7, 1.2, -0.2).astype(np.float32)
    B = np.asarray(planar_basis(jnp.asarray(vm)))
    assert B.shape == (6, 3)
    np.testing.assert_allclose(B.T @ B, np.eye(3), atol=1e-6)  # orthonormal
    moved = np.asarray(perturb_viewmat(jnp.asarray(vm), jnp.asarray(B) @ jnp.array([0.3, 0.2, -0.5])))
    assert abs(_centre(moved)[2] - 1.2) < 1e-5  # height
    np.testing.assert_allclose(moved[:3, 2], vm[:3, 2], atol=1e-6)  # world up seen from the camera: no roll/pitch
    assert np.linalg.norm(_centre(moved)[:2] - _centre(vm)[:2]) > 0.1  # it did move
    # a full 6-DoF increment projected on the plane keeps height and tilt too
    off = np.asarray(perturb_viewmat(jnp.asarray(vm), jnp.array([0.01, 0.02, 0.03, 0.04, 0.05, 0.06])))
    p = project_planar(off, vm)
    assert abs(_centre(p)[2] - 1.2) < 1e-5
    np.testing.assert_allclose(p[:3, 2], vm[:3, 2], atol=1e-6)


def test_planar_tracking_recovers_an_in_plane_offset(tracking_map):
    m, f = tracking_map
    B = planar_basis(jnp.asarray(f.viewmat))
    noisy = np.asarray(perturb_viewmat(jnp.asarray(f.viewmat), B @ jnp.array([0.015, 0.015, -0.012])))
    ang0, d0 = pose_distance(noisy, f.viewmat)
    r = track(m.map, f.rgb, f.depth, noisy, m.K, m.W, m.H, solver="adam", iters=80, planar=True)
    ang, d = pose_distance(r.viewmat, f.viewmat)
    assert r.status == "ok" and r.loss < r.loss0
    assert d < 0.005 and ang < np.radians(0.3), (d0, ang0, d, ang)
    assert abs(_centre(r.viewmat)[2] - _centre(f.viewmat)[2]) < 1e-4
    np.testing.assert_allclose(r.viewmat[:3, 2], f.viewmat[:3, 2], atol=1e-5)


def test_bad_lr_final_is_rejected():
    from splatsearch.slam import TrackerConfig

    with pytest.raises(ValueError, match="lr_final"):
        TrackerConfig(lr_final=0.0).validate()
    with pytest.raises(ValueError, match="lr_final"):
        TrackerConfig(lr_final=1.5).validate()
