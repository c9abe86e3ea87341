"""benchmarks/olivia_llu_trace.py: the doorway's opening, a plan's door passage and the seed lists."""

import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))

import olivia_llu_trace as lt  # noqa: E402

from splatsearch.social.convoi.scenarios import ROBOT_RADIUS, WALL, make_scenario  # noqa: E402


def test_door_of_finds_the_opening_between_the_wall_ends():
    scn = make_scenario("doorway", 300, door_width=1.3)
    x, lo, hi = lt.door_of(scn)
    assert x == 5.0
    assert abs((hi - lo) - (1.3 - 2 * WALL)) < 1e-6
    assert lt.door_of(make_scenario("hallway", 0)) is None


def test_door_passage_through_blocked_short():
    door = (5.0, -0.5, 0.5)
    assert lt.door_passage(np.array([[4.0, 0.0], [6.0, 0.1]]), door, ROBOT_RADIUS) == "through"
    assert lt.door_passage(np.array([[4.0, 0.4], [6.0, 0.4]]), door, ROBOT_RADIUS) == "blocked"  # body hits the post
    assert lt.door_passage(np.array([[1.0, 0.0], [4.9, 0.0]]), door, ROBOT_RADIUS) == "short"
    assert lt.door_passage(np.array([[1.0, 0.0], [6.0, 0.0]]), None, ROBOT_RADIUS) == "short"


def test_plan_geometry_reads_the_robot_frame():
    pose = np.array([4.0, 0.0, 0.0])
    t = np.linspace(0.1, 1.0, 10)
    straight = np.stack([2.4 * t, 0 * t, 0 * t], -1)
    right = np.stack([1.5 * t, -1.2 * t, 0 * t], -1)
    g = lt.plan_geometry(np.stack([straight, right]), pose, (5.0, -0.5, 0.5), ROBOT_RADIUS)
    assert g[0]["action"] == "straight" and g[0]["door"] == "through" and g[0]["advance"] == 2.4
    assert g[1]["action"] == "keep_right" and g[1]["lateral"] == -1.2 and g[1]["door"] == "blocked"


def test_parse_seeds():
    assert lt.parse_seeds("300-302,309") == [300, 301, 302, 309]


def _digest(index=0, oncoming=1):
    plan = {"action": "straight", "advance": 2.0, "lateral": 0.1, "door": "short"}
    return {"t": 10, "time_s": 1.0, "pose": [1.0, 0.0, 0.0], "oncoming": oncoming, "retrieved": 3,
            "retrieved_action": "keep_right", "similarity": 0.96, "view_entry": True, "text_used": True, "index": index,
            "logits": [0.0, -1.0], "safety": [0.0, 0.0], "consistency": [0.0, 0.0], "map": [0.0, 0.0],
            "score": [0.0, -1.0], "plans": [plan, dict(plan, action="keep_right", lateral=-1.0)],
            "walker_best": 1, "walker": dict(plan, action="keep_right", lateral=-0.8)}


def test_markdown_digest_of_a_partial_and_a_full_report():
    m = {"seed": 309, "mse": 0.5, "haus": 1.0, "reached": True, "psv": 0.0, "final_y": 0.0, "min_y": -0.1,
         "ref_min_y": -1.3}
    rep = {"checkpoint": "x.npz", "overrides": {}, "before": [m], "traces": {"309": {"before": [_digest()]}}}
    assert "| 309 | 0.5000 | 0.5000 |" in lt.markdown(rep)  # before-episodes only (a run cut short)
    rep |= {"buffer": [{"episode": 329, "oncoming": 1, "action": "keep_right", "caption": "c"}], "db_before": 10,
            "db_after": 12, "llu_losses": [2.0, 1.0], "after": []}
    rep["traces"]["309"]["same_state"] = [{"t": 10, "oncoming": 1, "index_before": 0, "index_after": 1,
                                           "text_used_after": True}]
    text = lt.markdown(rep)
    assert "head-on tagged {'keep_right': 1}" in text and "index changed on 1 of 1 (head-on: 1 of 1)" in text
    rep["after"] = [dict(m, mse=0.2)]
    rep["traces"]["309"]["after"] = [_digest(index=1)]
    text = lt.markdown(rep)
    assert "| 309 | 0.5000 | 0.2000 |" in text and "mean MSE before 0.5000, after 0.2000" in text
    s = lt.summarise_plans([_digest(), _digest(index=1, oncoming=0)])
    assert s["oncoming_plans"] == 1 and s["chosen_actions"] == {"straight": 1, "keep_right": 1}
    assert s["walker_best_chosen"] == 0.5
