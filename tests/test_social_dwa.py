"""JAX DWA: dynamic window, rollouts, critics, fallback, and closed-loop corridor runs."""

import jax.numpy as jnp
import numpy as np
import pytest
from splatsearch.nav.grid import GridSpec
from splatsearch.social.convoi import costs
from splatsearch.social.convoi.costs import CriticSpec
from splatsearch.social.convoi.dwa import (
    DEFAULT_CRITICS,
    DWAConfig,
    dynamic_window,
    make_inputs,
    navigate,
    plan,
    reference_critic,
    rollout,
    sample_velocities,
)
from splatsearch.social.convoi.geometry import distance_field_from_capsules, field_lookup

# a 3 m wide, 10 m long corridor with a pillar (r = 0.3 m) slightly left of its centre line
PILLAR = (5.0, 0.1, 0.3)
CAPS = np.array([[0, -1.5, 10, -1.5, 0.05], [0, 1.5, 10, 1.5, 0.05], [PILLAR[0], PILLAR[1], PILLAR[0], PILLAR[1], PILLAR[2]]],
                np.float32)
FIELD = distance_field_from_capsules(CAPS, GridSpec((-1.0, -2.0), 0.05, (80, 240)))
GOAL = np.array([9.5, 0.0], np.float32)


def drive(cfg, ref=None, steps=300):
    poses, _, fb = navigate(make_inputs([0.5, 0.0, 0.0], [0.0, 0.0], GOAL, FIELD, cfg, ref=ref), cfg, steps)
    poses = np.asarray(poses)
    reached = np.flatnonzero(np.linalg.norm(poses[:, :2] - GOAL, axis=1) < 0.3)
    end = reached[0] + 1 if len(reached) else len(poses)
    return poses[:end], int(np.asarray(fb).sum())


def side_at_pillar(traj):
    near = traj[np.abs(traj[:, 0] - PILLAR[0]) < 0.3]
    assert len(near), "the robot never reached the pillar"
    return float(np.mean(near[:, 1]))


def test_dynamic_window_respects_accelerations_and_limits():
    cfg = DWAConfig(v_max=0.6, w_max=1.0, acc_v=1.0, acc_w=2.0, control_dt=0.1)
    w = np.asarray(dynamic_window(jnp.array([0.55, -0.95]), cfg))
    np.testing.assert_allclose(w, [0.45, 0.6, -1.0, -0.75], atol=1e-6)
    s = np.asarray(sample_velocities(jnp.array([0.3, 0.0]), cfg))
    assert s.shape == (cfg.n_v * cfg.n_w, 2)
    assert s[:, 0].min() == pytest.approx(0.2) and s[:, 0].max() == pytest.approx(0.4)
    assert s[:, 1].min() == pytest.approx(-0.2) and s[:, 1].max() == pytest.approx(0.2)


def test_rollouts_follow_circular_arcs():
    samples = jnp.array([[0.5, 0.0], [0.4, 0.8], [0.0, 1.0]])
    tr = np.asarray(rollout(jnp.array([1.0, 2.0, 0.3]), samples, 0.1, 30))
    assert tr.shape == (3, 30, 3)
    np.testing.assert_allclose(tr[0, -1], [1 + 1.5 * np.cos(0.3), 2 + 1.5 * np.sin(0.3), 0.3], atol=1e-5)
    # constant (v, w): the exact arc of radius v / w
    t, R = 3.0, 0.5
    th = 0.3 + 0.8 * t
    np.testing.assert_allclose(tr[1, -1], [1 + R * (np.sin(th) - np.sin(0.3)), 2 - R * (np.cos(th) - np.cos(0.3)), th],
                               atol=2e-5)
    np.testing.assert_allclose(tr[2, -1, :2], [1.0, 2.0], atol=1e-6)


def test_collisions_are_infinite_and_free_samples_finite():
    cfg = DWAConfig()
    r = plan(make_inputs([4.2, 0.1, 0.0], [0.6, 0.0], GOAL, FIELD, cfg), cfg)
    costs_ = np.asarray(r.costs)
    v = np.asarray(r.samples)[:, 0]
    w = np.asarray(r.samples)[:, 1]
    straight_fast = (v > 0.55) & (np.abs(w) < 0.03)
    assert np.isinf(costs_[straight_fast]).all()  # head-on into the pillar, too fast to brake
    assert np.isfinite(costs_).any() and bool(r.feasible) and not bool(r.fallback)
    assert np.isfinite(float(r.cost))


def test_explicit_fallback_when_boxed_in():
    # a person right in front and walking into the robot: nothing is collision-free
    cfg = DWAConfig()
    r = plan(make_inputs([2.0, 0.0, 0.0], [0.5, 0.0], GOAL, FIELD, cfg, people=[[2.45, 0.0]], people_vel=[[-1.0, 0.0]]),
             cfg)
    assert not bool(r.feasible) and bool(r.fallback)
    assert np.isinf(np.asarray(r.costs)).all()
    v_lo = float(np.asarray(dynamic_window(jnp.array([0.5, 0.0]), cfg))[0])
    assert float(r.cmd[0]) == pytest.approx(v_lo, abs=1e-6)  # it brakes as hard as it can


def test_corridor_with_pillar_reaches_goal_without_collision():
    traj, fallbacks = drive(DWAConfig())
    assert np.linalg.norm(traj[-1, :2] - GOAL) < 0.3
    clearance = np.asarray(field_lookup(FIELD, jnp.asarray(traj[:, :2])))
    assert clearance.min() > DWAConfig().robot_radius  # never touched a wall or the pillar
    assert fallbacks == 0


@pytest.mark.parametrize("side", [1.0, -1.0])
def test_reference_path_cost_passes_on_the_reference_side(side):
    ref = np.array([[2.5, 0.5], [4.0, 0.9], [5.0, 0.9], [6.0, 0.9], [7.5, 0.5], [9.0, 0.0]], np.float32)
    ref[:, 1] *= side
    cfg = DWAConfig().with_critic(reference_critic())
    traj, _ = drive(cfg, ref)
    assert np.linalg.norm(traj[-1, :2] - GOAL) < 0.3
    y = side_at_pillar(traj)
    assert np.sign(y - PILLAR[1]) == side and abs(y - PILLAR[1]) > PILLAR[2] + 0.25
    assert np.asarray(field_lookup(FIELD, jnp.asarray(traj[:, :2]))).min() > cfg.robot_radius


def test_reference_gate_switches_the_cost_off_when_the_goal_is_out_of_view():
    cfg = DWAConfig().with_critic(reference_critic(theta_fov=0.5))
    ref = [[1.5, 1.0]]
    ahead = plan(make_inputs([0.5, 0, 0], [0.3, 0], [9.5, 0.0], FIELD, cfg, ref=ref), cfg)
    behind = plan(make_inputs([0.5, 0, 0], [0.3, 0], [-5.0, 0.3], FIELD, cfg, ref=ref), cfg)
    k = [c.name for c in cfg.critics].index("reference_path")
    assert np.asarray(ahead.critic_costs[k]).max() > 0.1
    assert np.asarray(behind.critic_costs[k]).max() == 0.0


def test_critic_registry_and_validation():
    @costs.register_critic("prefer_left_test")
    def prefer_left(inp, cfg, gain: float = 1.0):
        return -gain * inp.traj[:, -1, 1]

    cfg = DWAConfig(critics=DEFAULT_CRITICS + (CriticSpec.make("prefer_left_test", 50.0, normalize=False, gain=1.0),))
    r = plan(make_inputs([0.5, 0, 0], [0.3, 0.0], GOAL, FIELD, cfg), cfg)
    assert float(r.cmd[1]) > 0  # the strong custom critic turns the robot left
    with pytest.raises(ValueError, match="unknown critic"):
        CriticSpec.make("no_such_critic", 1.0)
    with pytest.raises(ValueError):
        DWAConfig(v_max=0.0)
    with pytest.raises(ValueError, match="pose"):
        make_inputs([0, 0], [0, 0], GOAL, FIELD, DWAConfig())
    with pytest.raises(ValueError, match="max_people"):
        make_inputs([0, 0, 0], [0, 0], GOAL, FIELD, DWAConfig(), people=np.zeros((20, 2)))
