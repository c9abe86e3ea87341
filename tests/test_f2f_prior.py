"""The frame-to-frame rotation prior: OpenCV RGB-D odometry between raw frames, its gate against
the wheel odometry, and how it reaches the tracker."""

import math

import numpy as np
import pytest

from splatsearch import odometry_f2f, sim, slam
from splatsearch.datasets.sim import walk_poses
from splatsearch.odometry_f2f import f2f_step, gate_step, planar_yaw_only, prior_step, rotation_angle


@pytest.fixture(scope="module")
def turn_pair():
    """Two 320x240 simulator frames of house 0: a 3 degree turn and a 4 cm step forward."""
    env = sim.HouseEnv(sim.make_house(0), width=320, height=240)
    x, y, yaw = walk_poses(env, 0, 1)[0]
    dyaw = math.radians(3.0)
    poses = [(x, y, yaw), (x + 0.04 * math.cos(yaw), y + 0.04 * math.sin(yaw), yaw + dyaw)]
    vms = [sim.camera_viewmat(*p).astype(np.float64) for p in poses]
    frames = [env.render_view(vm.astype(np.float32)) for vm in vms]
    return env.K, frames, vms


def _yaw_about(R, up):
    w = odometry_f2f.cv2.Rodrigues(np.asarray(R, np.float64))[0].ravel()
    return float(w @ up)


def test_f2f_recovers_a_known_turn_and_passes_the_gate(turn_pair):
    K, (a, b), (vm0, vm1) = turn_pair
    true = vm1 @ np.linalg.inv(vm0)
    step = f2f_step(a.rgb, a.depth, b.rgb, b.depth, K)
    assert step is not None
    up = vm0[:3, 2]  # the world's vertical in the first camera's frame
    step = planar_yaw_only(step, up)
    assert rotation_angle(step[:3, :3] @ true[:3, :3].T) < math.radians(0.1)
    # the wheel odometry's step: 0.5 degrees of extra yaw, 5 mm short
    R_odo = odometry_f2f.cv2.Rodrigues(up.reshape(3, 1) * math.radians(0.5))[0] @ true[:3, :3]
    odo = np.eye(4)
    odo[:3, :3] = R_odo
    odo = prior_step(true, odo)
    odo[:3, 3] *= 0.875
    assert rotation_angle(odo[:3, :3] @ true[:3, :3].T) > math.radians(0.4)
    cfg = slam.TrackerConfig(planar=True)
    assert gate_step(step, odo, *cfg.prior_sigma(odo))
    # the prediction takes the frame-to-frame rotation and the odometry's displacement
    pred = prior_step(odo, step)
    np.testing.assert_allclose(pred[:3, :3], step[:3, :3], atol=1e-12)
    disp = lambda s: -s[:3, :3].T @ s[:3, 3]  # noqa: E731
    np.testing.assert_allclose(disp(pred), disp(odo), atol=1e-12)
    assert abs(_yaw_about(pred[:3, :3], up) - _yaw_about(true[:3, :3], up)) < math.radians(0.1)
    assert abs(abs(_yaw_about(true[:3, :3], up)) - math.radians(3.0)) < 1e-6


def test_gate_rejects_a_disagreeing_estimate():
    odo = np.eye(4)
    odo[:3, 3] = [0, 0, -0.1]  # 10 cm forward (camera z)
    sr, st = slam.TrackerConfig().prior_sigma(odo)
    turned = odo.copy()
    turned[:3, :3] = odometry_f2f.cv2.Rodrigues(np.array([0.0, 4 * sr, 0.0]))[0]
    turned = prior_step(odo, turned)
    shifted = odo.copy()
    shifted[:3, 3] = [4 * st, 0, -0.1]
    assert gate_step(odo, odo, sr, st)
    assert not gate_step(turned, odo, sr, st)
    assert not gate_step(shifted, odo, sr, st)
    assert not gate_step(None, odo, sr, st)


def test_config_defaults_and_validation():
    from splatsearch.tracking_args import DEFAULTS, JACOBIANS, SOLVERS

    cfg = slam.TrackerConfig()
    assert cfg.f2f_prior is True and cfg.f2f_rot_sigma == 1e-3
    # the CLI's help shows tracking_args.DEFAULTS without importing JAX: they must be TrackerConfig's
    assert {k: getattr(cfg, k) for k in DEFAULTS} == DEFAULTS
    assert SOLVERS == slam.SOLVERS
    assert JACOBIANS == slam.JACOBIANS
    assert cfg.f2f_trans_sigma is None
    for bad in (0.0, -1e-3, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="f2f_rot_sigma"):
            slam.TrackerConfig(f2f_rot_sigma=bad).validate()
        with pytest.raises(ValueError, match="f2f_trans_sigma"):
            slam.TrackerConfig(f2f_trans_sigma=bad).validate()
        with pytest.raises(ValueError, match="f2f_max_depth_diff"):
            slam.TrackerConfig(f2f_max_depth_diff=bad).validate()


def test_cli_tracking_flags_parse():
    from splatsearch.cli import build_parser
    from splatsearch.tracking_args import flags_needing_track, tracker_config

    p = build_parser()
    a = p.parse_args(["map", "--track", "--no-track-f2f-prior", "--track-f2f-rot-sigma", "0.002",
                      "--track-gn-loss-tol", "0.001", "--track-prior-lateral", "off"])
    c = tracker_config(a)
    assert (c.f2f_prior, c.f2f_rot_sigma, c.gn_loss_tol, c.prior_lateral_sigma) == (False, 0.002, 0.001, None)
    assert set(flags_needing_track(a)) == {"--track-f2f-prior", "--track-f2f-rot-sigma", "--track-gn-loss-tol",
                                           "--track-prior-lateral"}
    unset = p.parse_args(["map"])
    assert flags_needing_track(unset) == [] and tracker_config(unset).prior_lateral_sigma == 0.01
    for bad in (["--track-prior-lateral", "sideways"], ["--track-f2f-rot-sigma", "0"], ["--track-gn-loss-tol", "-1"]):
        with pytest.raises(SystemExit):
            p.parse_args(["map", "--track", *bad])


def test_accepted_rotation_replaces_the_odometry_rotation_in_the_prior(turn_pair, tracker_start):
    """SLAM hands the tracker the frame-to-frame rotation and its tight sigma; without the prior,
    the wheel odometry's."""
    K, (a, b), (vm0, vm1) = turn_pair
    c, s_ = math.cos(math.radians(0.6)), math.sin(math.radians(0.6))
    rz = np.array([[c, -s_, 0, 0], [s_, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    centre = np.eye(4)
    centre[:3, 3] = np.linalg.inv(vm1)[:3, 3]
    odo1 = vm1 @ centre @ rz @ np.linalg.inv(centre)  # the odometry's heading 0.6 degrees off, same position
    seen = tracker_start
    odo1[:3, 3] += odo1[:3, :3] @ np.array([0.004, 0.0, 0.0])  # and 4 mm off sideways
    disp = lambda vm: np.linalg.inv(vm)[:3, 3]  # noqa: E731
    for on, trans in ((True, None), (False, None), (True, 2e-3)):
        cfg = slam.TrackerConfig(planar=True, f2f_prior=on, f2f_trans_sigma=trans)
        s = slam.SLAM(K, 320, 240, tracker_config=cfg)
        s.process(a.rgb, a.depth, vm0.astype(np.float32), odometry=vm0)
        with pytest.raises(RuntimeError, match="stop"):
            s.process(b.rgb, b.depth, odometry=odo1)
        err = math.degrees(rotation_angle(seen["init"][:3, :3] @ vm1[:3, :3].T))
        pos_err = float(np.linalg.norm(disp(seen["init"]) - disp(vm1)))
        if trans is not None:  # OpenCV's displacement too
            assert err < 0.1 and pos_err < 2e-3, (err, pos_err)
            assert seen["q"][3, 3] == pytest.approx(cfg.prior_weight / trans ** 2)
        elif on:
            assert err < 0.1 and pos_err > 3e-3, (err, pos_err)
            assert seen["q"][0, 0] == pytest.approx(cfg.prior_weight / cfg.f2f_rot_sigma ** 2)
        else:
            assert err > 0.5, err
            assert seen["q"][0, 0] == pytest.approx(cfg.prior_weight / cfg.prior_rot_sigma ** 2)
