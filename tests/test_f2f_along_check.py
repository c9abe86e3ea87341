"""TrackerConfig.f2f_along_check: an accepted link whose along-path distance disagrees with the wheel
odometry's by more than k odometry sigmas gives the rotation prior only (opt-in)."""

import numpy as np
import pytest

from splatsearch import slam as slam_mod
from splatsearch.mapper import MapperConfig
from splatsearch.slam import SLAM, TrackerConfig


def _forward(dz):
    """A world-to-camera step of a camera moving dz m along its +z axis."""
    s = np.eye(4)
    s[2, 3] = -dz
    return s


def _untrusted(monkeypatch, cv_dz, odo_dz, **cfg):
    """One accepted link: OpenCV says the camera moved cv_dz m forward, the odometry odo_dz m."""
    monkeypatch.setattr(slam_mod.odometry_f2f, "f2f_step", lambda *a, **k: _forward(cv_dz))
    monkeypatch.setattr(slam_mod.odometry_f2f, "gate_step", lambda *a, **k: True)
    s = SLAM(np.array([[50.0, 0, 16], [0, 50.0, 12], [0, 0, 1]]), 32, 24, MapperConfig(),
             TrackerConfig(f2f_retry_depth_diff=None, f2f_along_distrust=None, planar=False, **cfg))
    rgb, depth = np.zeros((24, 32, 3), np.float32), np.ones((24, 32), np.float32)
    s._f2f_reset(rgb, depth, np.eye(4))
    assert s._f2f_link_to(rgb, depth, _forward(odo_dz)) == "accepted"
    return s._f2f_untrusted


def test_off_by_default_and_validated():
    assert TrackerConfig().f2f_along_check is None
    for bad in (0.0, -1.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="f2f_along_check"):
            TrackerConfig(f2f_along_check=bad).validate()


def test_fires_beyond_k_odometry_sigmas_only(monkeypatch):
    tc = TrackerConfig()
    sigma = tc.prior_sigma(_forward(0.10))[1]  # 0.05 x 0.10 m + 1 mm = 6 mm
    assert np.isclose(sigma, 0.006)
    # OpenCV 1.5 sigma short of the odometry's 10 cm: fires at k = 1, not at k = 2, never when off
    assert _untrusted(monkeypatch, 0.10 - 1.5 * sigma, 0.10, f2f_along_check=1.0)
    assert not _untrusted(monkeypatch, 0.10 - 1.5 * sigma, 0.10, f2f_along_check=2.0)
    assert not _untrusted(monkeypatch, 0.10 - 1.5 * sigma, 0.10)
    # either sign
    assert _untrusted(monkeypatch, 0.10 + 2.5 * sigma, 0.10, f2f_along_check=2.0)
    # a link without motion is never checked
    assert not _untrusted(monkeypatch, 0.0005, 0.0, f2f_along_check=0.01)
