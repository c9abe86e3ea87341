"""OLiVia-Nav's route around the standing people it has perceived (hand-made scene; fast)."""

import jax.numpy as jnp
import numpy as np

from splatsearch.social.convoi.pedsim import make_state
from splatsearch.social.convoi.perception import visible_people
from splatsearch.social.convoi.scenarios import MAX_PEOPLE, PERSON_RADIUS, Scenario, check_capsules
from splatsearch.social.olivia.route import STAND_TIME, PerceivedRoute

# a 15 m x 10 m room; a group of three stands on the straight line from start to goal, and a
# 3 m wall at x = 2 hides a second group (behind it, off the line) from the start
GROUP = np.array([[5.0, 0.0], [5.7, 0.6], [5.7, -0.6]])
HIDDEN = np.array([[3.5, 3.0], [4.2, 3.4]])
WALLS = [[-1.5, -5.0, 13.5, -5.0, 0.05], [13.5, -5.0, 13.5, 5.0, 0.05], [13.5, 5.0, -1.5, 5.0, 0.05],
         [-1.5, 5.0, -1.5, -5.0, 0.05], [2.0, 1.5, 2.0, 4.5, 0.05]]


def _scene() -> Scenario:
    pos = np.vstack([GROUP, HIDDEN])
    peds = make_state(pos, [[p] for p in pos], [0.6] * len(pos), radius=PERSON_RADIUS, max_people=MAX_PEOPLE)
    return Scenario("test", 0, check_capsules(WALLS), np.array([0.0, 0.0, 0.0], np.float32),
                    np.array([11.0, 0.0], np.float32), peds)


def _clearance(path: np.ndarray, people: np.ndarray) -> float:
    return float(np.min(np.linalg.norm(path[:, None] - people[None], axis=-1)))


def _perceive(scn: Scenario, xy) -> tuple[np.ndarray, np.ndarray]:
    caps, valid = scn.padded_capsules()
    pos = np.asarray(scn.peds.pos)
    seen = np.asarray(visible_people(jnp.asarray([*xy, 0.0]), jnp.asarray(pos), jnp.asarray(scn.peds.active),
                                     jnp.asarray(caps), jnp.asarray(valid)))
    return pos, seen


def test_a_seen_standing_group_is_avoided_and_an_unseen_one_is_not():
    scn = _scene()
    walls = scn.global_path()
    assert _clearance(walls, GROUP) < 0.3  # the walls-only route runs through the group
    pos, seen = _perceive(scn, (0.0, 0.0))
    assert seen[:3].all() and not seen[3:5].any()  # the hidden group is behind the wall
    route = PerceivedRoute(scn, berth=0.8)
    # no second sweep yet: nobody's speed is known, the route stays the walls-only one
    assert route.update(pos, np.zeros_like(pos), seen, 0.0, measured=False) is walls
    path = route.update(pos, np.zeros_like(pos), seen, 0.3)
    assert _clearance(path, GROUP) > PERSON_RADIUS + 0.6
    # never through the group: the route passes wholly on one side of it
    at = np.abs(path[:, 0] - GROUP[:, 0].mean()) < 0.8
    assert np.all(path[at, 1] > GROUP[:, 1].max()) or np.all(path[at, 1] < GROUP[:, 1].min())
    assert route.replans == 1
    # the same perception again: no re-route
    route.update(pos, np.zeros_like(pos), seen, 2.0)
    assert route.replans == 1


def test_walking_people_are_not_avoided_and_a_group_that_walks_off_is_forgotten():
    scn = _scene()
    pos, seen = _perceive(scn, (0.0, 0.0))
    route = PerceivedRoute(scn, berth=0.8)
    walking = np.zeros_like(pos)
    walking[:3] = [-1.0, 0.0]
    for t in (0.0, 0.2, 2.0):
        assert route.update(pos, walking, seen, t) is route.walls
    assert route.replans == 0
    # seen walking, then a brief stop (to let the robot by): not standing
    route.update(pos, np.zeros_like(pos), seen, 2.2)
    route.update(pos, walking, seen, 2.4)
    route.update(pos, np.zeros_like(pos), seen, 2.6)
    assert route.update(pos, np.zeros_like(pos), seen, 2.6 + 0.5 * STAND_TIME) is route.walls
    route.update(pos, np.zeros_like(pos), seen, 2.6 + STAND_TIME)
    assert _clearance(route.path, GROUP) > PERSON_RADIUS + 0.6
    # they start walking: the route goes back to the walls-only one
    assert route.update(pos, walking, seen, 4.0) is route.walls


def test_zero_berth_keeps_the_walls_only_route():
    scn = _scene()
    pos, seen = _perceive(scn, (0.0, 0.0))
    route = PerceivedRoute(scn, berth=0.0)
    assert route.update(pos, np.zeros_like(pos), seen, 5.0) is route.walls


def test_perceived_berth_is_stored_and_defaults_for_older_checkpoints(tmp_path):
    import argparse
    import dataclasses

    from splatsearch.social.olivia.cli import register_olivia
    from splatsearch.social.olivia.planner import OliviaConfig
    from splatsearch.social.olivia.train import config_from_meta, config_to_meta

    meta = config_to_meta(dataclasses.replace(OliviaConfig(), perceived_berth=0.5))
    assert config_from_meta({"config": meta}).perceived_berth == 0.5
    del meta["perceived_berth"]  # a checkpoint from before the perceived route gets it
    assert config_from_meta({"config": meta}).perceived_berth == OliviaConfig().perceived_berth > 0
    parser = argparse.ArgumentParser()
    register_olivia(parser.add_subparsers(dest="cmd"))
    args = parser.parse_args(["eval", "--checkpoint", str(tmp_path / "none.npz"), "--perceived-berth", "-1"])
    assert args.func(args) == 2
