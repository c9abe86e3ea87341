"""OLiVia-Nav's plan selection at a head-on meeting (hand-made plans and people; fast)."""

import dataclasses

import numpy as np
import pytest

from splatsearch.social.olivia.features import HORIZON
from splatsearch.social.olivia.planner import OliviaConfig
from splatsearch.social.olivia.selection import forecast_people, oncoming_mask, selection_scores

T = 0.4 * np.arange(1, HORIZON + 1)  # the plans' instants (s)
STRAIGHT = np.stack([0.6 * T, 0 * T], -1)  # on at 0.6 m/s
_X = np.minimum(0.6 * T, 1.6)
ASIDE = np.stack([_X, -1.2 * _X / 1.6], -1)  # 1.2 m to the right over 1.6 m, then stand
LEFT = ASIDE * np.array([1.0, -1.0])
POSE = np.zeros(3)
PREV = np.vstack([[0.0, 0.0], STRAIGHT])  # the followed plan goes straight on
LOGITS = np.array([0.0, -1.5])  # the networks prefer straight on
OLD = dataclasses.replace(OliviaConfig(), oncoming_yield=False, cross_tau=0.0)  # constant velocity, symmetric


NEW = dataclasses.replace(OliviaConfig(), cross_tau=1.0)  # the head-on forecast (opt-in)


def _pick(people, vel, cfg=NEW, cand=(STRAIGHT, ASIDE)):
    p = selection_scores(LOGITS, np.stack(cand), POSE, PREV, 0.2, np.asarray(people, float).reshape(-1, 2),
                         np.asarray(vel, float).reshape(-1, 2), None, cfg)
    return int(np.argmax(p["score"])), p


def test_sidestep_is_picked_for_a_person_coming_head_on():
    # 3.5 m ahead, walking at the robot and drifting to its right (as through a door, seed 309)
    diag = ([[3.5, 0.5]], [[-0.85, -0.38]])
    k, p = _pick(*diag)
    assert p["oncoming"] == 1 and k == 1
    # with a constant-velocity forecast and a symmetric commitment it stayed in its lane
    assert _pick(*diag, cfg=OLD)[0] == 0
    # straight at the robot: the sidestep too, also with the default constant-velocity forecast
    assert _pick([[3.5, 0.0]], [[-1.0, 0.0]])[0] == 1
    assert _pick([[3.5, 0.0]], [[-1.0, 0.0]], cfg=OliviaConfig())[0] == 1
    assert _pick([[3.5, 0.0]], [[-1.0, 0.0]], cfg=OLD)[0] == 0  # held in its lane by the commitment


@pytest.mark.parametrize("people, vel", [
    (np.zeros((0, 2)), np.zeros((0, 2))),  # nobody
    ([[2.0, 0.0]], [[0.8, 0.0]]),  # walking ahead, away from the robot
    ([[3.0, 2.5]], [[0.0, -1.0]]),  # crossing, still far from the line
    ([[3.0, 0.9]], [[0.0, 0.0]]),  # standing beside the way
    ([[-2.0, 0.3]], [[1.0, 0.0]]),  # catching up from behind
])
def test_the_robot_keeps_its_lane_when_nobody_comes_head_on(people, vel):
    k, p = _pick(people, vel)
    assert p["oncoming"] == 0 and k == 0
    # and nothing changes against the old rule
    np.testing.assert_allclose(p["score"], _pick(people, vel, cfg=OLD)[1]["score"])


def test_the_commitment_still_holds_against_a_move_to_the_left():
    _, p = _pick([[3.5, 0.5]], [[-0.85, -0.38]], cand=(ASIDE, LEFT))
    assert p["consistency"][1] > 4 * p["consistency"][0]
    _, q = _pick([[3.5, 0.5]], [[-0.85, -0.38]], cfg=OLD, cand=(ASIDE, LEFT))
    assert q["consistency"][1] == pytest.approx(p["consistency"][1])


def test_the_forecast_bounds_a_head_on_persons_drift_across():
    people = np.array([[3.5, 0.5], [3.0, 2.5]])
    vel = np.array([[-0.85, -0.38], [0.0, -1.0]])  # one head-on, one crossing
    on = oncoming_mask(POSE, people, vel)
    assert on.tolist() == [True, False]
    cv = forecast_people(people, vel, HORIZON)
    f = forecast_people(people, vel, HORIZON, POSE, on, cross_tau=1.0)
    np.testing.assert_allclose(f[:, 1], cv[:, 1])  # the crossing person: constant velocity
    u = -people[0] / np.linalg.norm(people[0])  # toward the robot
    across = vel[0] - (vel[0] @ u) * u
    off = (f[:, 0] - people[0]) - T[:, None] * (vel[0] @ u) * u
    assert np.all(np.linalg.norm(off, axis=-1) <= np.linalg.norm(across) * 1.0 + 1e-9)
    np.testing.assert_allclose((f[:, 0] - people[0]) @ u, T * (vel[0] @ u))  # along: constant velocity
    np.testing.assert_allclose(forecast_people(people, vel, HORIZON, POSE, on, cross_tau=0.0), cv)


def test_head_on_reaches_as_far_as_a_meeting_within_the_horizon():
    people, vel = np.array([[5.5, 0.3]]), np.array([[-0.9, -0.1]])
    assert not oncoming_mask(POSE, people, vel)[0]  # beyond the fixed 4 m
    assert oncoming_mask(POSE, people, vel, meet_time=4.0)[0]  # (0.9 + 0.6) m/s x 4 s = 6 m
    assert not oncoming_mask(POSE, people * 1.5, vel, meet_time=4.0)[0]


def test_route_ahead_follows_the_route_from_its_nearest_point():
    from splatsearch.social.olivia.planner import route_ahead

    path = np.stack([np.linspace(0, 10, 101), np.zeros(101)], -1)
    r = route_ahead(path, np.array([4.0, -0.9]), HORIZON)
    assert r.shape == (HORIZON + 1, 2) and np.allclose(r[0], [4.0, -0.9])
    np.testing.assert_allclose(r[1:, 0], 4.0 + 0.24 * np.arange(1, HORIZON + 1))
    assert np.allclose(r[1:, 1], 0.0)
    np.testing.assert_allclose(route_ahead(path, np.array([9.9, 0.0]), 3)[1:], [[10.0, 0.0]] * 3)


def test_eval_refuses_a_negative_route_berth(tmp_path):
    import argparse

    from splatsearch.social.olivia.cli import register_olivia

    parser = argparse.ArgumentParser()
    register_olivia(parser.add_subparsers(dest="cmd"))
    args = parser.parse_args(["eval", "--checkpoint", str(tmp_path / "none.npz"), "--route-berth", "-1"])
    assert args.func(args) == 2
    assert parser.parse_args(["eval"]).route_berth is None  # the checkpoint's setting
    args = parser.parse_args(["eval", "--checkpoint", str(tmp_path / "none.npz"), "--cross-tau", "-0.5"])
    assert args.func(args) == 2
