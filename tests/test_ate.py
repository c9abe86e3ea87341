"""ATE (TUM evaluate_ate: rigid Horn/Umeyama alignment, RMSE of positions) and TUM trajectory files."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from splatsearch.trajectory import ate, camera_centres, read_tum, rotation_to_quat, umeyama_alignment, write_tum


def _viewmats(centres, rng):
    """World-to-camera matrices with the given camera centres and random orientations."""
    out = []
    for c in centres:
        c2w = np.eye(4)
        c2w[:3, :3] = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        c2w[:3, 3] = c
        out.append(np.linalg.inv(c2w))
    return np.array(out)


def test_rigidly_moved_copy_has_zero_ate():
    rng = np.random.default_rng(0)
    gt = _viewmats(rng.normal(size=(20, 3)), rng)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zyx", [40, -20, 75], degrees=True).as_matrix()
    T[:3, 3] = [1.5, -3.0, 0.7]
    # the same cameras in another world frame: c2w' = T c2w, so viewmat' = viewmat T^-1
    est = gt @ np.linalg.inv(T)
    np.testing.assert_allclose(camera_centres(est), camera_centres(gt) @ T[:3, :3].T + T[:3, 3], atol=1e-9)
    r = ate(est, gt)
    assert r["rmse"] < 1e-9 and r["n"] == 20
    np.testing.assert_allclose(r["R"], T[:3, :3].T, atol=1e-9)
    # without alignment the same copy is far off
    assert ate(est, gt, align=False)["rmse"] > 1.0


def test_known_offset_gives_known_ate():
    rng = np.random.default_rng(1)
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    gt = _viewmats(square, rng)
    # +-e along z at alternate corners: zero mean and uncorrelated with x and y, so no rigid
    # motion reduces it and every camera is off by exactly e
    e = 0.03
    est = _viewmats(square + np.array([[0, 0, e], [0, 0, -e], [0, 0, e], [0, 0, -e]]), rng)
    r = ate(est, gt)
    assert r["rmse"] == pytest.approx(e, abs=1e-9)
    assert r["max"] == pytest.approx(e, abs=1e-9) and r["median"] == pytest.approx(e, abs=1e-9)
    # a constant shift is removed by the alignment, but not without it
    shifted = _viewmats(square + [0.0, 0.05, 0.0], rng)
    assert ate(shifted, gt)["rmse"] < 1e-9
    assert ate(shifted, gt, align=False)["rmse"] == pytest.approx(0.05, abs=1e-9)


def test_non_finite_poses_are_left_out_and_errors_are_clear():
    rng = np.random.default_rng(2)
    gt = _viewmats(rng.normal(size=(6, 3)), rng)
    est = gt.copy()
    est[2] = np.nan
    r = ate(est, gt)
    assert r["n"] == 5 and r["rmse"] < 1e-9
    with pytest.raises(ValueError, match="length"):
        ate(est[:4], gt)
    with pytest.raises(ValueError, match="finite"):
        ate(np.full_like(gt, np.nan), gt)
    with pytest.raises(ValueError):
        umeyama_alignment(np.zeros((3, 2)), np.zeros((3, 2)))


def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(30, 3))
    R = Rotation.random(random_state=4).as_matrix()
    dst = 2.5 * src @ R.T + [1, 2, 3]
    R2, t2, s2 = umeyama_alignment(src, dst, with_scale=True)
    np.testing.assert_allclose(R2, R, atol=1e-9)
    np.testing.assert_allclose(t2, [1, 2, 3], atol=1e-9)
    assert s2 == pytest.approx(2.5)


def test_tum_trajectory_round_trip(tmp_path):
    rng = np.random.default_rng(5)
    vms = _viewmats(rng.normal(size=(7, 3)), rng)
    vms[3] = np.nan  # a lost frame is not written
    ts = 1305031102.0 + 0.033 * np.arange(7)
    p = tmp_path / "traj.txt"
    assert write_tum(str(p), ts, vms) == 6
    ts2, vms2 = read_tum(str(p))
    keep = [0, 1, 2, 4, 5, 6]
    np.testing.assert_allclose(ts2, ts[keep], atol=1e-6)
    np.testing.assert_allclose(vms2, vms[keep], atol=1e-5)
    for R in Rotation.random(50, random_state=6).as_matrix():
        q = rotation_to_quat(R)
        np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), R, atol=1e-9)
    (tmp_path / "bad.txt").write_text("1.0 2.0 3.0\n")
    with pytest.raises(ValueError, match="timestamp tx ty tz"):
        read_tum(str(tmp_path / "bad.txt"))
