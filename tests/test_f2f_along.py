"""The along-path frame-to-frame prior (``TrackerConfig.f2f_along_sigma``): OpenCV's distance
along the wheel odometry's direction of motion, the odometry's displacement across it."""

import math

import numpy as np
import pytest

from splatsearch import odometry_f2f, slam
from splatsearch.odometry_f2f import along_step, camera_displacement


def _step(yaw: float, disp) -> np.ndarray:
    """World-to-camera step (4, 4) of a camera turning by ``yaw`` about its y axis and moving by
    ``disp`` (3,) in the previous camera's frame."""
    R = odometry_f2f.cv2.Rodrigues(np.array([0.0, yaw, 0.0]).reshape(3, 1))[0]
    out = np.eye(4)
    out[:3, :3] = R
    out[:3, 3] = -R @ np.asarray(disp, np.float64)
    return out


def test_along_step_takes_the_distance_from_opencv_and_the_side_from_the_odometry():
    odo = _step(0.01, [0.0, 0.0, 0.105])  # wheel odometry: 10.5 cm forward, 0.01 rad of yaw
    f2f = _step(0.012, [0.006, 0.001, 0.098])  # OpenCV: 9.8 cm forward, 6 mm sideways
    out = along_step(odo, f2f)
    d = camera_displacement(out)
    assert d == pytest.approx([0.0, 0.0, 0.098], abs=1e-12)  # OpenCV's forward, none of its sideways
    assert out[:3, :3] == pytest.approx(f2f[:3, :3])  # the accepted rotation, as prior_step
    # a step in place keeps the odometry's displacement (no direction to measure along)
    still = _step(0.1, [0.0, 0.0, 0.0])
    assert camera_displacement(along_step(still, f2f)) == pytest.approx([0.0, 0.0, 0.0], abs=1e-12)
    assert along_step(still, f2f) == pytest.approx(odometry_f2f.prior_step(still, f2f))


def test_along_sigma_validation():
    slam.TrackerConfig(f2f_along_sigma=3e-3).validate()
    for bad in (0.0, -1e-3, math.inf, math.nan):
        with pytest.raises(ValueError, match="f2f_along_sigma"):
            slam.TrackerConfig(f2f_along_sigma=bad).validate()
    assert slam.TrackerConfig().f2f_along_sigma == 1e-3  # the default since stop 46
    assert slam.TrackerConfig().f2f_retry_depth_diff == 0.15


def test_slam_hands_the_tracker_the_along_path_prior(monkeypatch, tracker_start):
    """With an accepted OpenCV step, the tracker's start moves by OpenCV's distance along the path
    and its prior precision is 1 / f2f_along_sigma^2 along it, the lateral one across it."""
    K = np.array([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]])
    true = _step(0.0, [0.0, 0.0, 0.10])
    odo_step = _step(0.0, [0.0, 0.0, 0.106])  # the odometry 6 mm long
    monkeypatch.setattr(odometry_f2f, "f2f_step", lambda *a, **k: true.copy())
    seen = tracker_start
    rgb = np.full((120, 160, 3), 0.5, np.float32)
    depth = np.full((120, 160), 2.0, np.float32)
    vm0 = np.eye(4)
    cfg = slam.TrackerConfig(f2f_along_sigma=2e-3)
    s = slam.SLAM(K, 160, 120, tracker_config=cfg)
    s.process(rgb, depth, vm0.astype(np.float32), odometry=vm0)
    with pytest.raises(RuntimeError, match="stop"):
        s.process(rgb, depth, odometry=odo_step @ vm0)
    assert camera_displacement(seen["init"]) == pytest.approx([0.0, 0.0, 0.10], abs=1e-6)
    q = seen["q"]
    assert q[5, 5] == pytest.approx(cfg.prior_weight / 2e-3 ** 2, rel=1e-6)  # along z, the motion
    s_lat = cfg.prior_lateral_sigma * 0.106 + cfg.prior_trans_floor
    assert q[3, 3] == pytest.approx(cfg.prior_weight / s_lat ** 2, rel=1e-6)


@pytest.mark.parametrize("retry", [None, 0.15])
def test_retry_with_a_looser_depth_limit(monkeypatch, retry):
    """A step OpenCV fails at f2f_max_depth_diff is tried again at f2f_retry_depth_diff."""
    K = np.array([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]])
    true = _step(0.1, [0.0, 0.0, 0.0])  # a turn in place, where the tight limit fails
    limits = []

    def fake_f2f(*a, max_depth_diff=0.07, **k):
        limits.append(max_depth_diff)
        return true.copy() if max_depth_diff > 0.1 else None

    monkeypatch.setattr(odometry_f2f, "f2f_step", fake_f2f)
    cfg = slam.TrackerConfig(f2f_retry_depth_diff=retry)
    cfg.validate()
    s = slam.SLAM(K, 160, 120, tracker_config=cfg)
    s._f2f_ref, s._f2f_ref_odom = (np.zeros((120, 160, 3), np.float32), np.ones((120, 160), np.float32)), np.eye(4)
    status = s._f2f_link_to(np.zeros((120, 160, 3), np.float32), np.ones((120, 160), np.float32), true)
    if retry is None:
        assert status == "failed" and limits == [0.07]
    else:
        assert status == "accepted" and limits == [0.07, 0.15]
        assert s._f2f_acc == pytest.approx(true)
    with pytest.raises(ValueError, match="f2f_retry_depth_diff"):
        slam.TrackerConfig(f2f_retry_depth_diff=0.0).validate()
