"""The look-again step (issue 23): viewpoint choice on a hand-made grid, the policy's trips, and an
agent episode that takes the extra frame and verifies again."""

import numpy as np
import pytest

from splatsearch import sim
from splatsearch.agent import AgentConfig, SplatSearchAgent
from splatsearch.agent.look_again import azimuths_of, choose_viewpoint, line_of_sight
from splatsearch.nav.fmm import FMMPlanner, Plan
from splatsearch.nav.grid import GridSpec, wrap_angle
from splatsearch.nav.occupancy import FREE, OCCUPIED, OccupancyGrid
from splatsearch.search.novel_views import hemisphere_viewpoints


def _room():
    """A 6 x 6 m room around (0, 0), a 0.5 m object at the centre, and a wall at x = -1.0 m that
    cuts off the west side: the robot at (2, 0) cannot reach it."""
    spec = GridSpec.centered((0.0, 0.0), (160, 160))
    occ = OccupancyGrid(spec)
    xy = spec.cell_to_world(np.stack(np.mgrid[0:160, 0:160], -1))
    inside = (np.abs(xy[..., 0]) < 3.0) & (np.abs(xy[..., 1]) < 3.0)
    occ.state[inside] = FREE
    occ.state[~inside] = OCCUPIED
    occ.state[np.hypot(xy[..., 0], xy[..., 1]) < 0.25] = OCCUPIED  # the object
    occ.state[np.abs(xy[..., 0] + 1.0) < 0.05] = OCCUPIED  # the wall
    D = FMMPlanner.from_occupancy(occ).distance_from(np.array([2.0, 0.0]))
    return spec, occ, D


def test_viewpoint_is_a_free_reachable_cell_facing_the_unseen_side():
    spec, occ, D = _room()
    centre = np.array([0.0, 0.0, 0.4])
    # seen from the east (azimuth 0); the last NVSM run's southern camera rendered mostly holes
    v = choose_viewpoint(centre, 0.3, spec, occ.occupied, D, [0.0],
                         view_azimuths=[np.pi / 2, -np.pi / 2], view_holes=[0.2, 0.8], distance=1.6)
    assert v is not None
    rc = spec.world_to_cell(v.xy)
    assert occ.state[rc[0], rc[1]] == FREE and np.isfinite(D[rc[0], rc[1]]) and v.path == D[rc[0], rc[1]]
    assert not occ.inflated()[rc[0], rc[1]]  # the robot fits there
    assert v.xy[0] > -1.0  # not behind the wall
    assert v.xy[1] < -0.5 and 1.2 <= np.hypot(*v.xy) <= 2.3  # the southern side, about 1.6 m away
    assert abs(wrap_angle(v.yaw - np.arctan2(-v.xy[1], -v.xy[0]))) < 1e-6  # facing the object
    assert abs(wrap_angle(v.azimuth)) >= np.radians(40)  # away from the seen side
    assert line_of_sight(occ.occupied, spec, v.xy, centre[:2], skip_end=0.3)
    # with the holes the other way round it looks from the north instead
    v2 = choose_viewpoint(centre, 0.3, spec, occ.occupied, D, [0.0],
                          view_azimuths=[np.pi / 2, -np.pi / 2], view_holes=[0.8, 0.2], distance=1.6)
    assert v2.xy[1] > 0.5
    # without NVSM holes: the side farthest from what was seen that the robot can reach (not the
    # west, behind the wall)
    v3 = choose_viewpoint(centre, 0.3, spec, occ.occupied, D, [0.0], distance=1.6)
    assert v3 is not None and v3.xy[0] > -1.0 and abs(wrap_angle(v3.azimuth)) >= np.radians(90)


def test_no_viewpoint_when_nothing_is_reachable_or_everything_was_seen():
    spec, occ, D = _room()
    centre = np.array([0.0, 0.0, 0.4])
    assert choose_viewpoint(centre, 0.3, spec, occ.occupied, np.full(spec.shape, np.inf), [0.0]) is None
    assert choose_viewpoint(centre, 0.3, spec, occ.occupied, D, [0.0], max_path=0.5) is None  # too far
    every_side = np.radians(np.arange(0, 360, 30))
    assert choose_viewpoint(centre, 0.3, spec, occ.occupied, D, every_side) is None
    with pytest.raises(ValueError, match="grid's shape"):
        choose_viewpoint(centre, 0.3, spec, occ.occupied[:10], D, [0.0])


def test_azimuths_of_cameras_around_an_object():
    vms = hemisphere_viewpoints([1.0, 2.0, 0.5], 1.5, 4, (30.0,))
    az = azimuths_of(vms, [1.0, 2.0, 0.5])
    np.testing.assert_allclose(np.degrees(wrap_angle(az)), [0.0, 90.0, -180.0, -90.0], atol=1e-6)


def test_look_again_config_and_cli_flags():
    import argparse

    from splatsearch.cli_config import add_config_flags, config_overrides

    cfg0 = AgentConfig()  # stop 45's defaults: confirm marginal matches, look again only after a refusal
    assert (cfg0.look_again, cfg0.look_again_after_refute, cfg0.confirm_below, cfg0.confirm_by) == (
        1, True, 18.0, "new_frame")
    for bad in ({"look_again": -1}, {"look_again_steps": 0}, {"look_again_distance": 0.0}):
        with pytest.raises(ValueError, match="look_again"):
            AgentConfig(**bad)
    ap = argparse.ArgumentParser()
    add_config_flags(ap, AgentConfig, "agent")
    args = ap.parse_args(["--agent.look_again", "2", "--agent.look_again_low", "8"])
    assert config_overrides(args, "agent") == {"look_again": 2, "look_again_low": 8.0}
    helps = {a.dest: a.help for a in ap._actions}
    assert "ambiguous" in helps["agent.look_again"] and "abandoned" in helps["agent.look_again_steps"]


@pytest.fixture(scope="module")
def episode():
    house = sim.make_house(3)
    env = sim.HouseEnv(house)
    return sim.make_episodes(house, 1, "val", seed=0, env=env)[0], env


class _Planner:
    """A planner stand-in: every cell is reachable, the plan moves until told it arrived."""

    def __init__(self, spec):
        self.spec, self.status = spec, "moving"

    def distance_from(self, xy):
        return np.zeros(self.spec.shape)

    def plan(self, *a, **k):
        return Plan("move_forward", self.status, 2.0 if self.status == "moving" else 0.0)

    def path(self, *a, **k):
        return np.zeros((0, 2))


def test_policy_walks_to_the_viewpoint_faces_the_object_captures_and_verifies_again(episode):
    ep, env = episode
    cfg = AgentConfig(colour_cue=False, look_again=1, look_again_steps=10, look_again_after_refute=False)
    agent = SplatSearchAgent(env.K, env.width, env.height, np.zeros((240, 320, 3), np.float32), ep.goal_class,
                             ep.start, config=cfg)
    db, policy = agent.db, agent.policy
    c = np.asarray(ep.start, float)
    e = db.add(ep.goal_class, [c[0] + 3.0, c[1], 0.5], c, bbox=(np.array([c[0] + 2.8, c[1] - 0.2, 0.0]),
                                                               np.array([c[0] + 3.2, c[1] + 0.2, 0.9]))).entry_id
    db.record_match(e, 11.0, 0, cfg.tau_m)  # one NVSM run, 11 inliers: between look_again_low and tau_m
    assert agent.verifier.is_ambiguous(db[e]) and not agent.verifier.is_ambiguous(
        db[db.add(ep.goal_class, [c[0] - 3.0, c[1], 0.5], c).entry_id])  # never verified: not ambiguous
    planner = _Planner(agent.explorer.spec)
    agent.explorer.planner = lambda: planner
    captured = []

    def capture(eid):
        captured.append(eid)
        db.record_match(eid, 20.0, 0, cfg.tau_m)  # seen from its other side, it passes tau_m

    assert policy.decide(c, 1, capture=capture) == ("move_forward", "look_again")
    assert policy.target_entry == e and policy.looks == {e: 1}
    planner.status = "reached"
    away = np.array([c[0], c[1], np.pi])  # there, but facing away from the object: it turns first
    assert policy.decide(away, 2, capture=capture)[1] == "look_again" and captured == []
    facing = np.array([c[0], c[1], 0.0])
    action, status = policy.decide(facing, 3, capture=capture)
    assert captured == [e] and status == "goal_reached"  # verified again, it is now the goal
    assert policy.look_log[-1]["outcome"] == "captured" and policy.look_log[-1]["e_max_after"] == 20.0
    # a trip that never arrives is abandoned after look_again_steps steps, and only look_again views
    # are taken per object
    db.entries[e].matched, db.entries[e].e_max = False, 11.0
    planner.status = "moving"
    policy.looks.clear()
    assert policy.decide(c, 10, capture=capture)[1] == "look_again"
    assert policy.decide(c, 20, capture=capture)[1] != "look_again"
    assert policy.look_log[-1]["outcome"] == "timeout" and policy.looks[e] == 1
    assert policy.decide(c, 21, capture=capture)[1] != "look_again"
    # look_again 0: no trips
    agent0 = SplatSearchAgent(env.K, env.width, env.height, np.zeros((240, 320, 3), np.float32), ep.goal_class,
                              ep.start, config=AgentConfig(colour_cue=False, look_again=0))
    e0 = agent0.db.add(ep.goal_class, [c[0] + 3.0, c[1], 0.5], c).entry_id
    agent0.db.record_match(e0, 11.0, 0, cfg.tau_m)
    agent0.explorer.planner = lambda: _Planner(agent0.explorer.spec)
    assert agent0.policy.decide(c, 1, capture=capture)[1] != "look_again"


def test_episode_with_look_again_takes_the_extra_frame_and_verifies_again(episode, monkeypatch):
    """A real episode in house 3 with the NVSM stubbed (its count ambiguous until the object has been
    looked at again): the robot walks to the viewpoint, faces the object, the frame joins the
    object's observations and the NVSM runs on it."""
    import splatsearch.agent.verification as verification
    from splatsearch.search import NVSMResult

    ep, env = episode
    calls = []

    def fake_verify(goal, gmap, centroid, K, width, height, **kw):
        frames = gmap
        n = 30 if any(np.allclose(f.viewmat, v) for f in frames for v in captured_viewmats) else 11
        calls.append((len(frames), n))
        vms = kw["viewmats"] if kw.get("viewmats") is not None else np.eye(4)[None]
        V = len(vms)
        return NVSMResult(0, n, np.full(V, n), n >= 15, vms, np.zeros((V, 4, 4, 3)), np.zeros((V, 4, 4), bool),
                          np.zeros((V, 4, 4, 3)), np.zeros((V, 4, 4), np.float32))

    monkeypatch.setattr(verification, "verify_object", fake_verify)
    monkeypatch.setattr(verification, "build_local_map", lambda frames, *a, **k: list(frames))
    captured_viewmats = []
    cfg = AgentConfig(colour_cue=False, look_again=1, look_again_after_refute=False, map_every=4,
                      match_observations=False)
    gf = sim.goal_image(env, ep)
    obs = env.reset(ep.start)
    agent = SplatSearchAgent(env.K, env.width, env.height, gf.rgb, ep.goal_class, obs.pose, config=cfg,
                             goal_frame=gf)
    real_capture = agent._look_again_capture

    def capture(eid):
        captured_viewmats.append(np.array(obs.viewmat, np.float32))
        real_capture(eid)

    agent._look_again_capture = capture
    statuses = []
    for _ in range(120):
        info = agent.act(obs.frame.rgb, obs.frame.depth, obs.viewmat, obs.pose, obs.frame)
        statuses.append(info.status)
        if agent.policy.look_log and agent.policy.look_log[-1]["outcome"] == "captured":
            break
        obs = env.step(info.action)
        if obs.done or info.action == "stop":
            break
    log = agent.policy.look_log
    assert "look_again" in statuses and log and log[-1]["outcome"] == "captured", (statuses, log)
    eid = log[-1]["entry"]
    kept = agent.perception.observations[eid]
    assert any(np.allclose(f.viewmat, captured_viewmats[-1]) for f in kept)  # the new frame is kept
    assert calls[-1][1] == 30 and agent.db[eid].matched  # the NVSM ran again, on it
    assert log[-1]["e_max_before"] == 11.0 and log[-1]["e_max_after"] == 30.0
    assert env.steps == len(statuses) - 1  # every look-again move was an episode step


def _marginal_match(ep, env, **cfg_kw):
    """An agent whose DB holds one entry 3 m east of the start, taken for the goal by 16 inliers
    (one NVSM run), and the planner stand-in; returns (agent, entry id, start pose, planner)."""
    cfg = AgentConfig(colour_cue=False, **cfg_kw)
    agent = SplatSearchAgent(env.K, env.width, env.height, np.zeros((240, 320, 3), np.float32), ep.goal_class,
                             ep.start, config=cfg)
    c = np.asarray(ep.start, float)
    e = agent.db.add(ep.goal_class, [c[0] + 3.0, c[1], 0.5], c,
                     bbox=(np.array([c[0] + 2.8, c[1] - 0.2, 0.0]), np.array([c[0] + 3.2, c[1] + 0.2, 0.9]))).entry_id
    agent.db.record_match(e, 16.0, 0, cfg.tau_m)
    planner = _Planner(agent.explorer.spec)
    agent.explorer.planner = lambda: planner
    return agent, e, c, planner


def test_confirm_trip_refutes_a_marginal_match_whose_new_frame_falls_below_tau_m(episode):
    ep, env = episode
    agent, e, c, planner = _marginal_match(ep, env, confirm_below=18.0, look_again=1, look_again_after_refute=True)
    policy, db = agent.policy, agent.db
    # a second, ambiguous entry west of the start: no look-again trip before a refutation
    amb = db.add(ep.goal_class, [c[0] - 3.0, c[1], 0.5], c,
                 bbox=(np.array([c[0] - 3.2, c[1] - 0.2, 0.0]), np.array([c[0] - 2.8, c[1] + 0.2, 0.9]))).entry_id
    db.record_match(amb, 12.0, 0, agent.cfg.tau_m)
    assert policy.needs_confirm(db[e]) and policy.goal_candidates() == [db[e]]

    def capture(eid):  # the new side: 11 inliers in this frame (e_max keeps the old 16)
        agent.verifier._note(eid, 11.0)
        db.record_match(eid, 11.0, 0, agent.cfg.tau_m)

    assert policy.decide(c, 1, capture=capture) == ("move_forward", "confirm")  # not straight to the goal
    planner.status = "reached"
    agent.verifier.new_step()
    action, status = policy.decide(np.array([c[0], c[1], 0.0]), 2, capture=capture)
    log = [x for x in policy.look_log if x["kind"] == "confirm"]
    assert log[-1]["outcome"] == "refuted" and log[-1]["count_new"] == 11.0 and log[-1]["e_max_after"] == 16.0
    assert policy.refuted == {e: 11.0} and db[e].matched and not policy.goal_candidates()
    # refuted, the ambiguous entry now gets its look-again trip; the refuted one is never a look target
    assert status == "look_again" and policy.target_entry == amb
    # in eq 20 the refuted entry counts with its new frame's 11; in the end-of-exploration fallback
    # with its e_max 16, above the ambiguous one's 12 (the refusal only withholds the early stop)
    policy._look = None
    assert policy._object_scores()[e].e_max == 11.0 and policy._object_scores()[amb].e_max == 12.0
    assert policy.choose_fallback().id == e
    # a later clear pass (e_max >= confirm_below) makes it the goal again
    db.record_match(e, 25.0, 0, agent.cfg.tau_m)
    assert not policy.is_refuted(db[e]) and policy.goal_candidates() == [db[e]]


def test_trip_log_keeps_the_viewpoint_geometry_and_the_entry_counts(episode):
    """The diagnostic fields of a confirm trip: where it looked from relative to the stored
    observation (azimuth gap, distances) and the entry's count log (step, kind, count)."""
    ep, env = episode
    agent, e, c, planner = _marginal_match(ep, env, confirm_below=18.0, look_again=1)
    policy = agent.policy
    # one stored observation from the start, 3 m west of the object (azimuth 180 deg around it)
    vm = np.eye(4)
    vm[:3, 3] = -np.array([c[0], c[1], 1.0])
    agent.perception.observations.add(e, np.zeros((4, 4, 3)), np.ones((4, 4)), vm)

    def capture(eid):
        agent.verifier._note(eid, 0.0, "crop")  # zeros are not logged
        agent.verifier._note(eid, 11.0, "nvsm")

    planner.status = "reached"
    agent.verifier.new_step()
    policy.decide(np.array([c[0], c[1], 0.0]), 1, capture=capture)
    g = policy.look_log[-1]["geometry"]
    assert policy.look_log[-1]["outcome"] == "refuted"
    assert len(g["seen_az_deg"]) == 1 and abs(abs(g["seen_az_deg"][0]) - 180.0) < 0.1
    assert g["seen_dist_m"] == [3.0] and 1.0 <= g["view_dist_m"] <= 2.5
    gap = abs((g["view_az_deg"] - 180.0 + 180.0) % 360.0 - 180.0)
    assert abs(g["gap_deg"] - gap) < 0.2 and g["gap_deg"] >= 40.0  # choose_viewpoint's novelty
    assert g["best_az_deg"] is None  # the 16 came without a camera
    assert agent.verifier.count_log[e] == [[1, "nvsm", 11.0]]


def test_confirm_trip_keeps_a_match_the_new_frame_confirms_and_is_off_by_default(episode):
    ep, env = episode
    agent, e, c, planner = _marginal_match(ep, env, confirm_below=18.0)
    policy = agent.policy
    planner.status = "reached"

    def capture(eid):
        agent.verifier._note(eid, 15.0)  # passes tau_m again on its own

    facing = np.array([c[0], c[1], 0.0])
    action, status = policy.decide(facing, 1, capture=capture)
    assert policy.look_log[-1]["outcome"] == "confirmed" and e in policy.confirmed
    assert status in ("goal_reached", "to_goal") and policy.target_entry == e
    # confirmed once: no second trip
    n = len(policy.look_log)
    policy.decide(facing, 2, capture=capture)
    assert len(policy.look_log) == n
    # a match at or above confirm_below needs no trip; with confirm_below 0 (off) none does
    agent.db.record_match(e, 18.0, 0, agent.cfg.tau_m)
    policy.confirmed.clear()
    assert not policy.needs_confirm(agent.db[e])
    agent0, e0, _, _ = _marginal_match(ep, env, confirm_below=0.0)
    assert not agent0.policy.needs_confirm(agent0.db[e0])
    assert agent0.policy.decide(facing, 1, capture=capture)[1] != "confirm"
    with pytest.raises(ValueError, match="confirm_below"):
        AgentConfig(confirm_below=-1.0)
    # at or below tau_m the band is empty: off (so that raising tau_m keeps a valid config)
    agent20, e20, _, _ = _marginal_match(ep, env, tau_m=20.0)
    agent20.db.record_match(e20, 20.0, 0, 20.0)
    assert agent20.policy.goal_candidates() and not agent20.policy.needs_confirm(agent20.db[e20])


def test_rival_check_looks_at_ambiguous_entries_before_a_marginal_match_stands(episode):
    ep, env = episode
    agent, e, c, planner = _marginal_match(ep, env, confirm_below=18.0, confirm_by="rivals", look_again=1,
                                           look_again_after_refute=True)
    policy, db = agent.policy, agent.db
    amb = db.add(ep.goal_class, [c[0] - 3.0, c[1], 0.5], c,
                 bbox=(np.array([c[0] - 3.2, c[1] - 0.2, 0.0]), np.array([c[0] - 2.8, c[1] + 0.2, 0.9]))).entry_id
    db.record_match(amb, 12.0, 0, agent.cfg.tau_m)
    gains = {amb: 12.0}

    def capture(eid):
        assert eid == amb  # never a trip to the marginal match itself
        db.record_match(eid, gains[eid], 0, agent.cfg.tau_m)

    # the marginal match (16) is the goal candidate, but the ambiguous rival gets its look first
    assert policy.decide(c, 1, capture=capture) == ("move_forward", "look_again")
    assert policy.target_entry == amb and policy.look_log == []
    planner.status = "reached"
    west = np.array([c[0], c[1], np.pi])
    # the rival stays at 12: no rival left, the match stands and the robot goes to it
    action, status = policy.decide(west, 2, capture=capture)
    assert [x["kind"] for x in policy.look_log] == ["rival"] and policy.look_log[-1]["outcome"] == "captured"
    assert e in policy.confirmed and status in ("goal_reached", "to_goal") and policy.target_entry == e
    assert policy.decide(west, 3, capture=capture)[1] != "look_again"
    # the same again, but the rival's other side lifts it to 30: it overtakes the marginal match
    agent, e, c, planner = _marginal_match(ep, env, confirm_below=18.0, confirm_by="rivals", look_again=1)
    policy, db = agent.policy, agent.db
    amb = db.add(ep.goal_class, [c[0] - 3.0, c[1], 0.5], c,
                 bbox=(np.array([c[0] - 3.2, c[1] - 0.2, 0.0]), np.array([c[0] - 2.8, c[1] + 0.2, 0.9]))).entry_id
    db.record_match(amb, 12.0, 0, agent.cfg.tau_m)
    gains[amb] = 30.0
    planner.status = "reached"
    action, status = policy.decide(west, 1, capture=capture)
    assert policy.goal_candidates()[0].id == amb and policy.target_entry == amb and status == "goal_reached"
    with pytest.raises(ValueError, match="confirm_by"):
        AgentConfig(confirm_by="vote")


def test_confirm_cli_flags_have_help():
    import argparse

    from splatsearch.cli_config import add_config_flags, config_overrides

    ap = argparse.ArgumentParser()
    add_config_flags(ap, AgentConfig, "agent")
    args = ap.parse_args(["--agent.confirm_below", "20", "--agent.confirm_by", "rivals",
                          "--agent.look_again_after_refute", "off"])
    assert config_overrides(args, "agent") == {"confirm_below": 20.0, "confirm_by": "rivals",
                                               "look_again_after_refute": False}
    helps = {a.dest: a.help for a in ap._actions}
    assert "marginal" in helps["agent.confirm_below"] and "rivals" in helps["agent.confirm_by"]
    assert "refuted" in helps["agent.look_again_after_refute"]
