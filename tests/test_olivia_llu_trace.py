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
