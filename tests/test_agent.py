"""The SplatSearch agent, the episode runner, the demo and the evaluation (short runs)."""

import json

import numpy as np
import pytest

from splatsearch import sim
from splatsearch.agent import (
    FALLBACK_MATCH_MARGIN,
    VARIANTS,
    AgentConfig,
    SplatSearchAgent,
    crop_around,
    resolve_variant,
)
from splatsearch.episode import run_episode
from splatsearch.evaluation import evaluate, house_seeds, markdown_table, summarise
from splatsearch.search import Detection
from splatsearch.sim.episodes import goal_image


@pytest.fixture(scope="module")
def episode():
    house = sim.make_house(3)
    env = sim.HouseEnv(house)
    return sim.make_episodes(house, 1, "val", seed=0, env=env)[0], env


def test_config_validation():
    with pytest.raises(ValueError, match="variant"):
        AgentConfig(variant="oracle")
    with pytest.raises(ValueError):
        AgentConfig(map_every=0)
    assert VARIANTS == ("splatsearch", "no_nvsm", "no_vcicn", "opencv_inpaint", "nearest_frontier", "gaussnav")
    with pytest.raises(ValueError, match="nvsm_fill"):
        AgentConfig(nvsm_fill="local")


def test_nvsm_fill_hands_the_online_map_to_the_verifier():
    from types import SimpleNamespace

    from splatsearch.agent import SplatSearchAgent

    online = object()
    for fill, expected in (("global", online), ("none", None)):
        fake = SimpleNamespace(cfg=AgentConfig(nvsm_fill=fill),
                               perception=SimpleNamespace(mapper=SimpleNamespace(map=online)))
        assert SplatSearchAgent._fill_map(fake) is expected


def test_variants_resolve_to_explicit_switches():
    full = resolve_variant(AgentConfig())
    assert full.frontier_terms and full.nvsm_during_search and full.match_observations and full.inpaint
    assert full.colour_cue and not full.identify_after_exploring and not full.observation_match_is_nvsm
    assert not resolve_variant(AgentConfig(match_observations=False)).match_observations
    assert not resolve_variant(AgentConfig(colour_cue=False)).colour_cue
    no_nvsm = resolve_variant(AgentConfig(variant="no_nvsm", match_observations=False))
    assert no_nvsm.match_observations and no_nvsm.observation_match_is_nvsm and not no_nvsm.nvsm_during_search
    assert not resolve_variant(AgentConfig(variant="no_inpaint")).inpaint
    nf = resolve_variant(AgentConfig(variant="nearest_frontier"))
    assert not nf.frontier_terms and nf.nvsm_during_search and not nf.match_observations
    gn = resolve_variant(AgentConfig(variant="gaussnav"))
    assert gn.identify_after_exploring and not gn.nvsm_during_search and not gn.frontier_terms


def test_short_episode_runs_and_is_judged(episode):
    ep, env = episode
    seen = []
    r = run_episode(ep, AgentConfig(map_every=2), env=env, max_steps=8,
                    on_step=lambda agent, obs, info: seen.append((info.action, info.status, agent.mapper.map.n_active)))
    assert r.steps == 8 and len(r.trajectory) == 9
    assert len(seen) == 8
    assert all(a in sim.ACTIONS for a, _, _ in seen)
    assert seen[0][1] == "look_around"  # a full look around comes first
    assert seen[-1][2] > 0  # the map grew
    assert r.success == (r.final_distance <= ep.success_distance)
    assert 0.0 <= r.spl <= 1.0 and (r.spl > 0) == r.success


def test_agent_rejects_bad_goal_class(episode):
    ep, env = episode
    with pytest.raises(ValueError):
        SplatSearchAgent(env.K, env.width, env.height, np.zeros((240, 320, 3), np.float32), "unicorn", ep.start)


def test_agent_checks_the_goal_image(episode):
    ep, env = episode
    gf = goal_image(env, ep)

    def make(goal, **kw):
        return SplatSearchAgent(env.K, env.width, env.height, goal, ep.goal_class, ep.start, **kw)

    for bad, match in ((gf.rgb[..., 0], "shape"), (np.dstack([gf.rgb, gf.rgb[..., :1]]), "shape"),
                       (gf.rgb[:20, :20], "at least 32 px"), (gf.rgb * 255.0, "divide it by 255"),
                       (np.where(gf.rgb > 0.5, np.nan, gf.rgb), "NaN")):
        with pytest.raises(ValueError, match=match):
            make(bad)
    with pytest.raises(TypeError, match="dtype"):
        make(gf.rgb.astype(np.int32))
    with pytest.raises(ValueError, match="goal_mask shape"):
        make(gf.rgb, goal_mask=np.ones((10, 10), bool))
    # another size than the robot camera is fine, and uint8 is read as 0-255
    small = (gf.rgb[::2, ::2] * 255 + 0.5).astype(np.uint8)
    agent = make(small, goal_frame=None)
    assert agent.goal.shape == (120, 160, 3) and agent.goal.dtype == np.float32
    np.testing.assert_allclose(agent.goal, small / 255.0, atol=1e-6)


class _BrokenDetector:
    """A plug-in that returns masks at the wrong size, or not Detections at all."""

    def __init__(self, out):
        self.out = out

    def detect(self, rgb, frame=None):
        return self.out(rgb)


def test_agent_reports_broken_detector_output(episode):
    ep, env = episode
    gf = goal_image(env, ep)
    obs = env.reset(ep.start)
    half = lambda rgb: [Detection(np.ones((rgb.shape[0] // 2, rgb.shape[1] // 2), bool), ep.goal_class, 0.9)]
    for out, err, match in ((half, ValueError, r"mask of shape \(120, 160\).*\(240, 320\)"),
                            (lambda rgb: [(np.ones(rgb.shape[:2], bool), ep.goal_class, 0.9)], TypeError,
                             "tuple at index 0"),
                            (lambda rgb: None, TypeError, "must return a list")):
        agent = SplatSearchAgent(env.K, env.width, env.height, gf.rgb, ep.goal_class, ep.start,
                                 detector=_BrokenDetector(out), goal_mask=gf.rgb[..., 0] > 2)
        with pytest.raises(err, match=match):
            agent.act(obs.frame.rgb, obs.frame.depth, obs.viewmat, obs.pose, obs.frame)
    # checked on the goal image too, where the agent looks for the goal object's mask
    with pytest.raises(ValueError, match="_BrokenDetector.detect returned a mask"):
        SplatSearchAgent(env.K, env.width, env.height, gf.rgb, ep.goal_class, ep.start, detector=_BrokenDetector(half))


def test_summary_and_table():
    rs = [{"variant": "a", "success": True, "spl": 0.5, "steps": 10, "wall_time": 2.0},
          {"variant": "a", "success": False, "spl": 0.0, "steps": 30, "wall_time": 4.0},
          {"variant": "b", "success": True, "spl": 1.0, "steps": 5, "wall_time": 1.0},
          {"variant": "b", "success": False, "spl": 0.0, "steps": 0, "wall_time": 0.1, "error": "ValueError: x"}]
    s = summarise(rs)
    assert s["a"] == {"n": 2, "SR": 0.5, "SPL": 0.25, "steps": 20.0, "median_wall_s": 3.0, "mean_wall_s": 3.0,
                      "errors": 0}
    # an episode that raised is a failure, and stays out of the step and time statistics
    assert s["b"]["SR"] == 0.5 and s["b"]["errors"] == 1 and s["b"]["steps"] == 5.0 and s["b"]["median_wall_s"] == 1.0
    md = markdown_table(s, "t")
    assert "| a | 2 | 0.500 | 0.250 | 20 | 3.0 | 0 |" in md
    assert house_seeds(0, 2) == [1000, 1001] and house_seeds(1, 1) == [1100]


def test_evaluate_writes_results(tmp_path):
    results, _ = evaluate("val", 1, seed=0, variants=("nearest_frontier",), out=str(tmp_path), max_steps=4)
    assert len(results) == 1 and results[0]["steps"] == 4
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["summary"]["nearest_frontier"]["n"] == 1
    assert (tmp_path / "summary.md").read_text().startswith("### val")
    with pytest.raises(ValueError):
        evaluate("val", 1, variants=("nope",))
    # resume keeps the finished episode and runs only the missing variant
    again, summary = evaluate("val", 1, seed=0, variants=("nearest_frontier", "no_nvsm"), out=str(tmp_path),
                              max_steps=4, resume=True)
    assert len(again) == 2 and again[0] == results[0] and again[1]["variant"] == "no_nvsm"
    assert summary["no_nvsm"]["n"] == 1
    with pytest.raises(ValueError, match="resume"):
        evaluate("val", 1, resume=True)
    # a resume in identical-furniture houses does not reuse episodes from the other houses
    ident, summary = evaluate("val", 1, seed=0, variants=("nearest_frontier",), out=str(tmp_path), max_steps=4,
                              resume=True, identical_furniture=True)
    assert len(ident) == 1 and ident[0]["identical_furniture"] and not results[0]["identical_furniture"]
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["identical_furniture"] and "identical furniture" in (tmp_path / "summary.md").read_text()
    # agent overrides reach every variant, and a resume with other overrides reruns
    feat, _ = evaluate("val", 1, seed=0, variants=("nearest_frontier",), out=str(tmp_path), max_steps=4,
                       resume=True, identical_furniture=True, agent_overrides={"colour_cue": False})
    assert len(feat) == 1 and feat[0]["agent_overrides"] == {"colour_cue": False}
    assert "colour_cue=False" in (tmp_path / "summary.md").read_text()
    for bad in ({"variant": "gaussnav"}, {"no_such_field": 1}):
        with pytest.raises(ValueError, match="agent_overrides"):
            evaluate("val", 1, agent_overrides=bad)


@pytest.mark.slow
def test_longer_episode_end_to_end(episode):
    """A whole val episode in house 3: the agent must find the goal and stop next to it (the
    simulator's judge, not the agent, decides success), having seen and verified objects."""
    ep, env = episode
    statuses = []
    r = run_episode(ep, AgentConfig(), env=env, max_steps=300, on_step=lambda a, o, i: statuses.append(i.status))
    assert r.success and r.status == "goal_reached" and r.final_distance <= ep.success_distance
    assert r.steps < 300 and r.n_objects >= 1 and 0.0 < r.spl <= 1.0
    assert statuses[0] == "look_around" and "to_goal" in statuses


def test_observation_crops_stay_matchable_for_sliver_masks():
    from splatsearch.search import SIFTMatcher

    rgb = np.random.default_rng(0).uniform(0, 1, (240, 320, 3)).astype(np.float32)
    mask = np.zeros((240, 320), bool)
    mask[10:114, 0:4] = True  # a 4-px sliver at the image border
    crop = crop_around(rgb, mask)
    assert crop.shape[0] >= 104 and crop.shape[1] >= 16
    SIFTMatcher().count(rgb, crop)  # no "image too small" error
    mask[:] = False
    mask[100:140, 100:180] = True
    assert crop_around(rgb, mask).shape == (80, 160, 3)  # grown by half the box each side


def test_agent_gives_up_a_goal_it_cannot_get_closer_to(episode):
    ep, env = episode
    agent = SplatSearchAgent(env.K, env.width, env.height, np.zeros((240, 320, 3), np.float32), ep.goal_class,
                             ep.start, config=AgentConfig(goal_patience=3))
    policy = agent.policy
    assert not policy.goal_stalled(0, 5.0)  # first distance: progress
    assert not policy.goal_stalled(0, 4.0)
    stalled = [policy.goal_stalled(0, 3.95) for _ in range(4)]  # less than 0.1 m closer each time
    assert stalled == [False, False, False, True]
    assert not policy.goal_stalled(1, 9.0)  # another goal starts afresh


def test_compile_cache_is_configurable(tmp_path, monkeypatch):
    import jax

    from splatsearch.compile_cache import ENV_VAR, enable_compile_cache

    old = jax.config.jax_compilation_cache_dir
    try:
        monkeypatch.setenv(ENV_VAR, "off")
        assert enable_compile_cache() is None
        with pytest.raises(ValueError, match="min_compile_seconds"):
            enable_compile_cache(str(tmp_path / "c"), -1.0)
        monkeypatch.setenv(ENV_VAR, str(tmp_path / "cache"))
        assert enable_compile_cache() == str(tmp_path / "cache")
        assert jax.config.jax_compilation_cache_dir == str(tmp_path / "cache") and (tmp_path / "cache").is_dir()
    finally:
        jax.config.update("jax_compilation_cache_dir", old)


def test_agent_keeps_a_matched_goal_while_the_way_to_it_is_unmapped(episode):
    from splatsearch.nav.fmm import Plan

    ep, env = episode
    agent = SplatSearchAgent(env.K, env.width, env.height, np.zeros((240, 320, 3), np.float32), ep.goal_class,
                             ep.start, config=AgentConfig(goal_patience=3))
    res = agent.db.add(ep.goal_class, np.array([ep.start[0] + 3.0, ep.start[1], 0.5]), np.asarray(ep.start, float))
    agent.db.record_match(res.entry_id, 40.0, 0, agent.cfg.tau_m)

    class Unmapped:  # the goal is not reachable on the map yet
        def plan(self, *a, **k):
            return Plan("stop", "unreachable", np.inf)

        def path(self, *a, **k):
            raise ValueError("no path")

    agent.explorer.planner = lambda: Unmapped()
    pose = np.asarray(ep.start, float)
    statuses = [agent.policy.decide(pose, 1)[1] for _ in range(10)]
    assert res.entry_id not in agent.policy.given_up  # ten unreachable steps do not count as stalling
    assert "stuck_goal" not in statuses
    assert statuses == ["look_around"] * 10  # it explores toward the goal meanwhile (first a look around)


def test_appearance_decides_which_objects_are_the_goal(episode):
    ep, env = episode

    gf = goal_image(env, ep)
    agent = SplatSearchAgent(env.K, env.width, env.height, gf.rgb, ep.goal_class, ep.start, goal_frame=gf)
    assert agent.perception.goal_signature is not None  # the detector found the goal object in the goal image
    assert agent.verifier.colour_cue
    db, c = agent.db, np.asarray(ep.start, float)
    look = db.add(ep.goal_class, [c[0] + 2, c[1], 0.5], c).entry_id  # looks like the goal
    other = db.add(ep.goal_class, [c[0] - 2, c[1], 0.5], c).entry_id  # another instance's colours
    for _ in range(2):
        db.record_colour(look, 0.6, 1.0)
        db.record_colour(other, 0.05, 1.0)
    db.record_match(other, 40.0, 0, agent.cfg.tau_m)  # a feature-match false positive
    assert agent.is_goal(db[look]) and not agent.is_goal(db[other])  # colours veto the match
    assert [e.id for e in agent.goal_candidates()] == [look]
    # matching could change neither decision, so neither object is matched or rendered any more
    assert not agent.verifier.can_decide(db[look]) and not agent.verifier.can_decide(db[other])
    one = db.add(ep.goal_class, [c[0], c[1] + 3, 0.5], c).entry_id
    db.record_colour(one, 0.9, 1.0)  # one view is not enough to confirm ...
    assert not agent.is_goal(db[one]) and agent.verifier.can_decide(db[one])
    db.record_match(one, 40.0, 0, agent.cfg.tau_m)  # ... but it does not veto a feature match
    assert agent.is_goal(db[one])
    # gaussnav decides only after exploring
    gn = SplatSearchAgent(env.K, env.width, env.height, gf.rgb, ep.goal_class, ep.start, goal_frame=gf,
                          config=AgentConfig(variant="gaussnav"))
    e = gn.db.add(ep.goal_class, [c[0] + 2, c[1], 0.5], c).entry_id
    gn.db.record_colour(e, 0.6, 1.0)
    gn.db.record_colour(e, 0.6, 1.0)
    assert gn.goal_candidates() == []
    gn.policy.explored = True
    assert [x.id for x in gn.goal_candidates()] == [e]


def test_agent_without_a_goal_mask_falls_back_to_feature_matching(episode):
    ep, env = episode
    agent = SplatSearchAgent(env.K, env.width, env.height, np.zeros((240, 320, 3), np.float32), ep.goal_class,
                             ep.start)  # no goal frame: the simulator detector cannot run on the goal image
    assert agent.perception.goal_signature is None and not agent.verifier.colour_cue
    r = agent.db.add(ep.goal_class, [0.0, 0.0, 0.5], np.asarray(ep.start, float))
    assert not agent.is_goal(agent.db[r.entry_id])
    agent.db.record_match(r.entry_id, 40.0, 0, agent.cfg.tau_m)
    assert agent.is_goal(agent.db[r.entry_id])
    with pytest.raises(ValueError, match="goal_mask shape"):
        SplatSearchAgent(env.K, env.width, env.height, np.zeros((240, 320, 3), np.float32), ep.goal_class,
                         ep.start, goal_mask=np.ones((10, 10), bool))
    with pytest.raises(ValueError, match="tau_a"):
        AgentConfig(tau_a=0.1, colour_veto=0.2)


def test_agent_matches_renders_and_camera_images_with_their_own_sift_settings(episode):
    from splatsearch.search import RENDER_CONTRAST_THRESHOLD, SIFTMatcher

    ep, env = episode
    goal = np.zeros((240, 320, 3), np.float32)
    agent = SplatSearchAgent(env.K, env.width, env.height, goal, ep.goal_class, ep.start)
    assert agent.verifier.matcher.contrast_threshold == 0.04  # camera images: OpenCV's default
    assert agent.verifier.nvsm_matcher.contrast_threshold == RENDER_CONTRAST_THRESHOLD < 0.04
    mine = SIFTMatcher(ratio=0.7)  # a user's matcher serves both unless an NVSM one is given
    agent = SplatSearchAgent(env.K, env.width, env.height, goal, ep.goal_class, ep.start, matcher=mine)
    assert agent.verifier.matcher is mine and agent.verifier.nvsm_matcher is mine
    other = SIFTMatcher(ratio=0.8)
    agent = SplatSearchAgent(env.K, env.width, env.height, goal, ep.goal_class, ep.start, matcher=mine,
                             nvsm_matcher=other)
    assert agent.verifier.matcher is mine and agent.verifier.nvsm_matcher is other


def test_nvsm_counts_are_judged_against_their_own_threshold(episode, monkeypatch):
    import splatsearch.agent.verification as verification
    from splatsearch.search import NVSMResult

    ep, env = episode
    with pytest.raises(ValueError, match="nvsm_tau_m"):
        AgentConfig(nvsm_tau_m=0)
    cfg = AgentConfig(tau_m=15, nvsm_tau_m=20, clear_views=False)
    agent = SplatSearchAgent(env.K, env.width, env.height, np.zeros((240, 320, 3), np.float32), ep.goal_class,
                             ep.start, config=cfg)
    counts = iter([16, 24])

    def fake_verify(goal, gmap, centroid, K, width, height, **kw):
        assert kw["matcher"] is agent.verifier.nvsm_matcher and kw["config"].tau_m == 20
        assert gmap == "local map" and kw["viewmats"] is None  # clear_views off: the plain hemisphere
        n = next(counts)
        return NVSMResult(0, n, np.array([n]), n >= 20, np.eye(4)[None], np.zeros((1, 4, 4, 3)),
                          np.zeros((1, 4, 4), bool), np.zeros((1, 4, 4, 3)))

    monkeypatch.setattr(verification, "verify_object", fake_verify)
    monkeypatch.setattr(verification, "build_local_map", lambda *a, **k: "local map")
    db, obs, v = agent.db, agent.perception.observations, agent.verifier
    r = db.add(ep.goal_class, [0.0, 0.0, 0.5], np.asarray(ep.start, float), bbox=(np.zeros(3), np.ones(3)))
    assert v.verify(db, r.entry_id, obs) is None and agent.nvsm_runs == 0  # no observation of it yet
    o = env.reset(ep.start)
    obs.add(r.entry_id, o.frame.rgb, o.frame.depth, o.viewmat)
    v.verify(db, r.entry_id, obs)  # 16 render inliers: above tau_m, below nvsm_tau_m
    e = db[r.entry_id]
    assert e.e_max == pytest.approx(16 * 15 / 20) and not e.matched
    v.verify(db, r.entry_id, obs)
    assert e.e_max == pytest.approx(24 * 15 / 20) and e.matched and agent.nvsm_runs == 2
    assert agent.last_views.entry_id == r.entry_id and agent.last_views.best == 0


def test_agent_walks_up_to_a_look_alike_and_gives_it_up_unconfirmed(episode):
    from splatsearch.nav.fmm import Plan

    ep, env = episode
    gf = goal_image(env, ep)
    agent = SplatSearchAgent(env.K, env.width, env.height, gf.rgb, ep.goal_class, ep.start, goal_frame=gf,
                             config=AgentConfig(verify_steps=4))
    c = np.asarray(ep.start, float)
    e = agent.db.add(ep.goal_class, [c[0] + 3.0, c[1], 0.5], c).entry_id
    agent.db.record_colour(e, 0.9, 1.0)  # looks like the goal, but from one viewpoint only
    assert agent.goal_candidates() == [] and [x.id for x in agent.policy.promising()] == [e]

    class Planner:
        status = "moving"

        def plan(self, *a, **k):
            return Plan("move_forward", self.status, 3.0 if self.status == "moving" else 0.0)

        def path(self, *a, **k):
            return np.zeros((0, 2))

    planner = Planner()
    agent.explorer.planner = lambda: planner
    policy = agent.policy
    assert policy.decide(c, 0) == ("move_forward", "to_candidate")
    planner.status = "reached"  # there: it turns to look but never stops at an unconfirmed object
    statuses = [policy.decide(c, step)[1] for step in range(1, 7)]
    assert statuses[:4] == ["verifying"] * 4 and statuses[4] == "not_the_goal"
    assert e in policy.given_up and policy.promising() == []


def test_end_of_exploration_fallback_is_chosen_again_with_hysteresis(episode):
    from splatsearch.nav.fmm import Plan

    ep, env = episode
    agent = SplatSearchAgent(env.K, env.width, env.height, np.zeros((240, 320, 3), np.float32), ep.goal_class,
                             ep.start, config=AgentConfig(colour_cue=False))
    c = np.asarray(ep.start, float)
    db, tau = agent.db, agent.cfg.tau_m
    a = db.add(ep.goal_class, [c[0] + 3.0, c[1], 0.5], c).entry_id
    b = db.add(ep.goal_class, [c[0] - 3.0, c[1], 0.5], c).entry_id
    db.record_match(a, 8.0, 0, tau)  # neither passes tau_m
    db.record_match(b, 7.0, 0, tau)

    class Planner:
        def plan(self, *a, **k):
            return Plan("move_forward", "moving", 3.0)

        def path(self, *a, **k):
            return np.zeros((0, 2))

    agent.explorer.planner = lambda: Planner()
    policy = agent.policy
    policy.explored = True
    assert agent.goal_candidates() == []  # the fallback is not taken for a matched goal
    assert policy.decide(c, 1) == ("move_forward", "to_goal") and agent.target_entry == a
    db.record_match(b, 8.0 + FALLBACK_MATCH_MARGIN - 1.0, 0, tau)  # a near-tie does not turn the robot
    policy.decide(c, 2)
    assert agent.target_entry == a
    db.record_match(b, 12.0, 0, tau)  # seen better on the way: the other entry takes over
    policy.decide(c, 3)
    assert agent.target_entry == b
    policy.given_up.add(b)  # and when it is given up, the next best is chosen
    policy.decide(c, 4)
    assert agent.target_entry == a
