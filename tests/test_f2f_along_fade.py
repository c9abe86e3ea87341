"""The along-path prior faded by the image's own information on the forward translation
(``TrackerConfig.f2f_along_fade``): its construction, and that it fades where the image pins the
forward motion."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from splatsearch import odometry_f2f, slam
from splatsearch.odometry_f2f import camera_displacement
from splatsearch.slam import perturb_viewmat, pose_distance, track
from splatsearch.tracking_gn import axis_information, fade_weight


def _step(disp) -> np.ndarray:
    """World-to-camera step (4, 4) moving the camera by ``disp`` (3,) in its own frame, no turn."""
    out = np.eye(4)
    out[:3, 3] = -np.asarray(disp, np.float64)
    return out


def test_fade_weight_keeps_what_the_image_does_not_supply():
    extra = jnp.float32(10.0)
    assert float(fade_weight(jnp.float32(0.0), extra)) == pytest.approx(1.0)  # the image says nothing
    assert float(fade_weight(jnp.float32(2.5), extra)) == pytest.approx(0.75)
    assert float(fade_weight(jnp.float32(10.0), extra)) == pytest.approx(0.0)  # it fixes the axis as well
    assert float(fade_weight(jnp.float32(50.0), extra)) == pytest.approx(0.0)  # never negative
    assert float(fade_weight(jnp.float32(1.0), jnp.float32(0.0))) == 0.0  # no extra prior: nothing to keep


def test_axis_information_is_the_marginal_information():
    H = jnp.array([[4.0, 0.0], [0.0, 9.0]])
    assert float(axis_information(H, jnp.array([0.0, 2.0]))) == pytest.approx(9.0, rel=1e-6)  # length ignored
    # a correlated pair: the other direction free, the information is the Schur complement
    H = jnp.array([[4.0, 3.0], [3.0, 9.0]])
    assert float(axis_information(H, jnp.array([0.0, 1.0]))) == pytest.approx(9.0 - 9.0 / 4.0, rel=1e-5)
    assert float(axis_information(H, jnp.zeros(2))) == 0.0


def _fake_track(seen):
    def fake(gmap, rgb, depth, init_viewmat, K, width, height, config=None, *, prior_precision=None, prior_fade=None,
             fade_axis=None, fade_scale=1.0, **kw):
        seen.update(init=np.asarray(init_viewmat, np.float64), q=prior_precision, pf=prior_fade, axis=fade_axis,
                    scale=fade_scale)
        raise RuntimeError("stop")
    return fake


@pytest.mark.parametrize("fade", [None, 0.5])
def test_slam_hands_the_tracker_the_faded_along_prior(monkeypatch, fade):
    """With f2f_along_fade the tracker gets the odometry's own along-path precision, and the rest of
    the along prior's (1 / f2f_along_sigma^2 minus that) as the faded part along the motion;
    without it, the whole along prior as before."""
    K = np.array([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]])
    monkeypatch.setattr(odometry_f2f, "f2f_step", lambda *a, **k: _step([0.0, 0.0, 0.10]))
    seen: dict = {}
    monkeypatch.setattr(slam, "track", _fake_track(seen))
    monkeypatch.setattr(slam.Mapper, "update", lambda self, *a, **k: {})
    cfg = slam.TrackerConfig(f2f_along_sigma=1e-3, f2f_along_fade=fade)
    s = slam.SLAM(K, 160, 120, tracker_config=cfg)
    rgb = np.full((120, 160, 3), 0.5, np.float32)
    depth = np.full((120, 160), 2.0, np.float32)
    s.process(rgb, depth, np.eye(4, dtype=np.float32), odometry=np.eye(4))
    odo = _step([0.0, 0.0, 0.106])  # the odometry 6 mm long
    with pytest.raises(RuntimeError, match="stop"):
        s.process(rgb, depth, odometry=odo)
    assert camera_displacement(seen["init"]) == pytest.approx([0.0, 0.0, 0.10], abs=1e-6)  # OpenCV's distance
    w, s_odo = cfg.prior_weight, cfg.prior_sigma(odo)[1]
    s_lat = cfg.lateral_sigma(odo)
    q = seen["q"]
    assert q[3, 3] == pytest.approx(w / s_lat ** 2, rel=1e-6)  # across the motion: unchanged
    assert abs(seen["axis"][2]) == pytest.approx(np.linalg.norm(seen["axis"]))  # the axis is the motion's
    if fade is None:
        assert seen["pf"] is None
        assert q[5, 5] == pytest.approx(w / 1e-3 ** 2, rel=1e-6)
    else:
        assert q[5, 5] == pytest.approx(w / s_odo ** 2, rel=1e-6)  # the odometry's own along sigma
        pf = seen["pf"]
        assert pf[5, 5] == pytest.approx(w * (1 / 1e-3 ** 2 - 1 / s_odo ** 2), rel=1e-6)
        assert np.count_nonzero(np.abs(pf) > 1e-9) == 1  # along the motion only
        assert q[5, 5] + pf[5, 5] == pytest.approx(w / 1e-3 ** 2, rel=1e-6)  # unfaded: stop 45's prior
        assert seen["scale"] == fade


def test_fade_validation():
    slam.TrackerConfig(f2f_along_fade=1.0).validate()
    for bad in (0.0, -1.0, math.inf, math.nan):
        with pytest.raises(ValueError, match="f2f_along_fade"):
            slam.TrackerConfig(f2f_along_fade=bad).validate()
    assert slam.TrackerConfig().f2f_along_fade is None


def test_the_prior_fades_where_the_image_fixes_the_forward_motion(tracking_map):
    """On a view of a wall, moving toward it changes every pixel's depth (high information), moving
    along it barely changes the render: the same extra prior is dropped on the first axis and
    mostly kept on the second, and a kept prior holds the pose nearer the prediction."""
    m, f = tracking_map
    noisy = np.asarray(perturb_viewmat(jnp.asarray(f.viewmat), jnp.array([0, 0.003, 0, 0.004, 0, 0.004])))
    kw = dict(solver="gn", planar=True, prior_sigma=(0.01, 0.01))
    plain = track(m.map, f.rgb, f.depth, noisy, m.K, m.W, m.H, **kw)
    toward = track(m.map, f.rgb, f.depth, noisy, m.K, m.W, m.H, fade_axis=np.array([0.0, 0.0, 1.0]), **kw)
    along = track(m.map, f.rgb, f.depth, noisy, m.K, m.W, m.H, fade_axis=np.array([1.0, 0.0, 0.0]), **kw)
    # measuring alone changes nothing
    np.testing.assert_array_equal(toward.viewmat, plain.viewmat)
    assert np.isnan(plain.fwd_info) and plain.fade == 0.0
    assert toward.fwd_info > 2.5 * along.fwd_info > 0, (toward.fwd_info, along.fwd_info)
    c = math.sqrt(toward.fwd_info * along.fwd_info) / 2  # an extra curvature 2c between the two
    for ax, res in ((np.array([0.0, 0.0, 1.0]), toward), (np.array([1.0, 0.0, 0.0]), along)):
        pf = np.zeros((6, 6))
        pf[3:, 3:] = c * np.outer(ax, ax)
        r = track(m.map, f.rgb, f.depth, noisy, m.K, m.W, m.H, fade_axis=ax, prior_fade=pf, **kw)
        assert r.fwd_info == pytest.approx(res.fwd_info, rel=1e-5)
        assert r.fade == pytest.approx(max(0.0, 1 - r.fwd_info / (2 * c)), abs=1e-5)
        if ax[2]:
            assert r.fade == 0.0
            np.testing.assert_array_equal(r.viewmat, plain.viewmat)
        else:
            assert r.fade > 0.3
    # a kept prior holds the translation nearer the prediction (a very tight one: all of it kept)
    pf = np.zeros((6, 6))
    pf[5, 5] = 1e9
    held = track(m.map, f.rgb, f.depth, noisy, m.K, m.W, m.H, fade_axis=np.array([0.0, 0.0, 1.0]), prior_fade=pf, **kw)
    assert held.fade > 0.99
    assert pose_distance(held.viewmat, noisy)[1] < 0.5 * pose_distance(plain.viewmat, noisy)[1]
    with pytest.raises(ValueError, match="fade_axis"):
        track(m.map, f.rgb, f.depth, noisy, m.K, m.W, m.H, prior_fade=pf, **kw)
