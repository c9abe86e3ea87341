"""The people forecast of OLiVia-Nav's plan selection (hand-made people; fast)."""

import argparse
import dataclasses

import numpy as np
import pytest

from splatsearch.social.olivia.features import HORIZON
from splatsearch.social.olivia.forecast import (REACT_BERTH, constant_velocity, forecast_people, plan_times,
                                                reactive_forecast)
from splatsearch.social.olivia.planner import OliviaConfig
from splatsearch.social.olivia.selection import safety_cost, selection_scores

POSE = np.zeros(3)  # at the origin, facing +x
# ahead and 0.2 m left of the robot's line, walking at it; ahead on the right; behind it, walking away
PEOPLE = np.array([[3.0, 0.2], [2.5, -0.4], [-2.0, 0.1]])
VEL = np.array([[-1.0, 0.0], [-0.8, 0.1], [-0.5, 0.0]])


def test_gain_zero_is_constant_velocity():
    cv = PEOPLE[None] + plan_times(HORIZON)[:, None, None] * VEL[None]
    np.testing.assert_allclose(constant_velocity(PEOPLE, VEL, HORIZON), cv)
    np.testing.assert_allclose(reactive_forecast(PEOPLE, VEL, HORIZON, POSE, 0.0), cv)
    np.testing.assert_allclose(forecast_people(PEOPLE, VEL, HORIZON, POSE, people_react=0.0), cv)


def test_a_person_ahead_makes_way_and_one_behind_does_not():
    cv = constant_velocity(PEOPLE, VEL, HORIZON)
    f = reactive_forecast(PEOPLE, VEL, HORIZON, POSE, 1.0)
    lat = f[..., 1] - cv[..., 1]  # the robot faces +x: its left is +y
    assert np.all(np.diff(lat[:, 0]) > 0) and lat[-1, 0] > 0.5  # steps left, off the robot's line
    assert lat[-1, 0] <= REACT_BERTH - 0.2 + 1e-9  # no farther than the berth
    assert np.all(np.diff(lat[:, 1]) < 0)  # the person on the right steps right
    np.testing.assert_allclose(f[:, 2], cv[:, 2])  # behind the robot: constant velocity
    np.testing.assert_allclose(f[..., 0], cv[..., 0])  # nobody is slowed down or sped up
    # a straight plan through them intrudes less once they make way; a faster reaction, less still
    straight = np.stack([0.6 * plan_times(HORIZON), np.zeros(HORIZON)], -1)[None]
    costs = [safety_cost(straight, PEOPLE, VEL, 0.45, POSE, people_react=g)[0] for g in (0.0, 0.5, 2.0)]
    assert costs[0] > costs[1] > costs[2]


def test_negative_gains_are_refused():
    with pytest.raises(ValueError, match="gain"):
        reactive_forecast(PEOPLE, VEL, HORIZON, POSE, -0.1)
    with pytest.raises(ValueError, match="people_react"):
        OliviaConfig(people_react=-1.0)
    with pytest.raises(ValueError, match="people_react"):
        OliviaConfig(people_react=float("nan"))


def test_the_flag_reaches_the_selection(tmp_path, monkeypatch):
    from types import SimpleNamespace

    from splatsearch.social.olivia import cli, planner, train

    parser = argparse.ArgumentParser()
    cli.register_olivia(parser.add_subparsers(dest="cmd"))
    assert parser.parse_args(["eval"]).people_react is None  # the checkpoint's setting
    args = parser.parse_args(["eval", "--checkpoint", str(tmp_path / "none.npz"), "--people-react", "-1"])
    assert args.func(args) == 2
    # the value given reaches the planner's config
    seen = {}

    class Stop(Exception):
        pass

    class Fake:
        params, db, cfg = {}, None, OliviaConfig()

    def fake_table_two(planner, *a, **k):
        seen["cfg"] = planner.cfg
        raise Stop

    monkeypatch.setattr(train, "load_planner", lambda path: Fake())
    monkeypatch.setattr(planner, "OliviaNav", lambda params, db, cfg: SimpleNamespace(cfg=cfg))
    monkeypatch.setattr(train, "table_two", fake_table_two)
    args = parser.parse_args(["eval", "--checkpoint", str(tmp_path / "none.npz"), "--people-react", "1.5",
                              "--no-table1", "--workers", "1", "--no-progress"])
    with pytest.raises(Stop):
        args.func(args)
    assert seen["cfg"].people_react == 1.5
    # ... survives a checkpoint header, and the selection's safety cost uses it
    assert train.config_from_meta({"config": train.config_to_meta(seen["cfg"])}).people_react == 1.5
    straight = np.stack([0.6 * plan_times(HORIZON), np.zeros(HORIZON)], -1)[None]
    parts = [selection_scores(np.zeros(1), straight, POSE, None, 0.0, PEOPLE, VEL, None,
                              dataclasses.replace(OliviaConfig(), people_react=g))["safety"][0] for g in (0.0, 1.5)]
    assert parts[1] < parts[0]
