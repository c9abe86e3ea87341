"""OLiVia-Nav navigation controller: PID loops and trajectory following."""

import jax.numpy as jnp
import numpy as np
import pytest
from splatsearch.social.convoi import metrics as M
from splatsearch.social.convoi.controller import (
    FollowerConfig,
    PIDGains,
    pid_init,
    pid_update,
    track,
)


def test_pid_terms_anti_windup_and_clamp():
    g = PIDGains(kp=2.0, ki=1.0, kd=0.5, i_limit=0.3, out_limit=10.0)
    u, st = pid_update(g, pid_init(), 1.0, 0.1)
    assert float(u) == pytest.approx(2.0 + 0.1 + 0.0)  # no derivative kick on the first step
    u, st = pid_update(g, st, 0.5, 0.1)
    assert float(u) == pytest.approx(1.0 + 0.15 + 0.5 * (0.5 - 1.0) / 0.1)
    for _ in range(100):
        u, st = pid_update(g, st, 1.0, 0.1)
    assert float(st.integral) == pytest.approx(0.3)  # clamped
    u, _ = pid_update(PIDGains(100.0, out_limit=1.5), pid_init(), 1.0, 0.1)
    assert float(u) == 1.5
    with pytest.raises(ValueError):
        PIDGains(-1.0)


def test_follower_tracks_an_s_curve_and_stops_at_its_end():
    t = np.linspace(0, 2 * np.pi, 200)
    traj = np.stack([1.2 * t, np.sin(t)], -1).astype(np.float32)
    cfg = FollowerConfig()
    poses, cmds = track(cfg, jnp.asarray(traj), jnp.array([0.0, 0.3, 0.0]), 0.1, 300)
    poses, cmds = np.asarray(poses), np.asarray(cmds)
    cross = np.array([np.linalg.norm(traj - p[:2], axis=1).min() for p in poses])
    assert cross[30:].max() < 0.08  # converged from a 0.3 m offset within 3 s, then stays on it
    assert np.linalg.norm(poses[-1, :2] - traj[-1]) < 0.1
    assert np.abs(cmds[-10:, 0]).max() < 0.05  # stopped
    assert cmds[:, 0].max() <= cfg.v_max + 1e-6 and np.abs(cmds[:, 1]).max() <= cfg.w_max + 1e-6
    assert np.abs(np.diff(cmds[:, 0])).max() <= cfg.acc_v * 0.1 + 1e-5  # acceleration limits
    assert M.frechet(poses[:, :2], traj) < 0.35  # the initial 0.3 m offset is the worst of it


def test_follower_turns_before_driving_when_the_path_is_behind():
    traj = np.array([[0.0, 0.0], [-1.0, 0.0], [-2.0, 0.0]], np.float32)
    poses, cmds = track(FollowerConfig(), jnp.asarray(traj), jnp.array([0.0, 0.0, 0.0]), 0.1, 150)
    cmds = np.asarray(cmds)
    assert np.abs(cmds[:5, 0]).max() < 0.05 and np.abs(cmds[:5, 1]).max() > 0.1
    assert np.linalg.norm(np.asarray(poses)[-1, :2] - traj[-1]) < 0.15
