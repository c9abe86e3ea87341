"""OLiVia-Nav data: renders, LiDAR, labels, captions, tokenizer (fast)."""

import jax.numpy as jnp
import numpy as np
import pytest

from splatsearch.social.convoi.scenarios import make_scenario
from splatsearch.social.olivia import captions, dataset, features, lidar, render
from splatsearch.social.olivia.tokenizer import DEFAULT_TOKENIZER as TOK, EOS, PAD, Tokenizer

F32 = jnp.float32


@pytest.fixture(scope="module")
def hallway():
    return make_scenario("hallway", 0)


def _people(P, pts):
    pos = np.full((P, 2), 1000.0, np.float32)
    pos[: len(pts)] = pts
    valid = np.zeros(P, bool)
    valid[: len(pts)] = True
    return jnp.asarray(pos), jnp.asarray(valid)


def test_render_shows_people_walls_and_floor(hallway):
    P = 12
    pos, valid = _people(P, [[3.0, 0.0]])
    palette = jnp.zeros(P, jnp.int32)  # everyone in red
    img = np.asarray(render.render_view(hallway.field(), jnp.asarray([0.0, 0.0, 0.0], F32), pos, valid, palette))
    assert img.shape == (render.IMG_H, render.IMG_W, 3) and img.dtype == np.float32
    assert 0 <= img.min() and img.max() <= 1
    red = np.all(np.abs(img - render.COLOUR_RGB[0]) < 0.25, -1)
    cols = np.flatnonzero(red.any(0))
    assert len(cols) > 0 and abs(cols.mean() - render.IMG_W / 2) < 4  # the person is straight ahead
    # the hallway walls (1.3 m either side) fill the image edges at eye level
    grey = lambda p: np.all(np.abs(p - p.mean()) < 0.05) and 0.2 < p.mean() < 0.75  # noqa: E731
    row = render.IMG_H // 2
    assert grey(img[row, 0]) and grey(img[row, -1])
    # floor below, ceiling above
    assert np.allclose(img[0, render.IMG_W // 2], render.CEIL_RGB, atol=0.02)
    assert img[-1, render.IMG_W // 2, 0] > img[-1, render.IMG_W // 2, 2]  # beige floor
    # a person behind the robot is not drawn; with nobody, no red pixels
    pos2, valid2 = _people(P, [[-1.0, 0.0]])
    img2 = np.asarray(render.render_view(hallway.field(), jnp.asarray([0.0, 0.0, 0.0], F32), pos2, valid2, palette))
    assert not np.all(np.abs(img2 - render.COLOUR_RGB[0]) < 0.25, -1).any()


def test_lidar_hits_walls_and_people(hallway):
    P = 12
    pos, valid = _people(P, [[2.0, 0.0]])
    pose = jnp.asarray([0.0, 0.0, 0.0], F32)
    pts, ok = lidar.lidar_points(hallway.field(), pose, pos, valid, pose, pos)
    pts, ok = np.asarray(pts), np.asarray(ok)
    assert pts.shape == (lidar.N_POINTS, 4) and ok.shape == (lidar.N_POINTS,)
    now = ok & (pts[:, 3] == 0)
    side = now & (np.abs(pts[:, 0]) < 0.5)  # beams straight left / right
    assert np.allclose(np.abs(pts[side, 1]), 1.25, atol=0.05)  # wall surface at 1.3 - 0.05 m
    ahead = now & (np.abs(pts[:, 1]) < 0.05) & (pts[:, 0] > 0)
    assert np.any(np.abs(pts[ahead, 0] - 1.75) < 0.05)  # the person's front at 2 - 0.25 m
    assert np.all((pts[now, 2] >= 0) & (pts[now, 2] <= render.WALL_HEIGHT + 1e-4))
    # the earlier sweep, from 0.5 m behind, lands in the current frame (motion compensated)
    prev = jnp.asarray([-0.5, 0.0, 0.0], F32)
    pts2, ok2 = lidar.lidar_points(hallway.field(), pose, pos, valid, prev, pos)
    old = np.asarray(ok2) & (np.asarray(pts2)[:, 3] == 1)
    ahead_old = old & (np.abs(np.asarray(pts2)[:, 1]) < 0.05) & (np.asarray(pts2)[:, 0] > 0)
    assert np.any(np.abs(np.asarray(pts2)[ahead_old, 0] - 1.75) < 0.05)


def test_action_of_classifies():
    t = np.linspace(0.1, 1.0, features.HORIZON)[:, None]
    z = 0 * t
    assert captions.ACTIONS[features.action_of(np.hstack([2.4 * t, z, z]))] == "straight"
    assert captions.ACTIONS[features.action_of(np.hstack([2.2 * t, -0.6 * t, z]))] == "keep_right"
    assert captions.ACTIONS[features.action_of(np.hstack([2.2 * t, 0.6 * t, z]))] == "keep_left"
    assert captions.ACTIONS[features.action_of(np.hstack([1.5 * t, 1.0 * t, 1.2 * t]))] == "turn_left"
    assert captions.ACTIONS[features.action_of(np.hstack([1.5 * t, -1.0 * t, -1.2 * t]))] == "turn_right"
    assert captions.ACTIONS[features.action_of(np.hstack([0.3 * t, z, z]))] == "yield"
    with pytest.raises(ValueError):
        features.action_of(np.zeros(5))


def test_future_in_frame_and_blending():
    poses = np.stack([np.arange(60) * 0.05, np.zeros(60), np.zeros(60)], -1)
    fut = features.future_in_frame(poses, 0, poses[0])
    assert fut.shape == (features.HORIZON, 3)
    np.testing.assert_allclose(fut[:, 0], 0.05 * features.FUTURE_STRIDE * np.arange(1, features.HORIZON + 1), atol=1e-5)
    # the end is repeated past the episode
    assert features.future_in_frame(poses, 55, poses[55])[-1, 0] == pytest.approx(0.05 * 4, abs=1e-5)
    # displaced 0.3 m to the left: the labels start there and blend back onto the expert's line
    frame = poses[0] + np.array([0.0, 0.3, 0.0])
    f2 = features.future_in_frame(poses, 0, frame, offset=np.array([0.0, 0.3]))
    assert f2[0, 1] == pytest.approx(-0.3 * 0.2, abs=1e-5)
    np.testing.assert_allclose(f2[features.HORIZON // 2:, 1], -0.3, atol=1e-5)


def test_goal_features(hallway):
    g = features.goal_features(hallway.global_path(), hallway.goal, np.array([0.0, 0.0, 0.0]))
    assert g.shape == (features.GOAL_DIM,)
    assert g[0] == pytest.approx(1.0, abs=0.05) and abs(g[1]) < 0.1  # 3 m straight ahead
    g2 = features.goal_features(hallway.global_path(), hallway.goal, np.array([0.0, 0.0, np.pi / 2]))
    assert g2[1] == pytest.approx(-1.0, abs=0.05)  # turned left: the carrot is on the right


def test_template_captions_carry_the_action_and_tokenize():
    for a, name in enumerate(captions.ACTIONS):
        scene = captions.CaptionScene("a corridor", "d", 0, np.array([[2.0, 0.5]]), np.array([[-1.0, 0.0]]),
                                np.array([2]), np.array([-1]), (1.2, 1.3, 9.0), a)
        for v in (0, 1):
            c = captions.TemplateCaptioner().caption(None, scene, variant=v)
            assert c.ok and c.action == a
            assert captions.action_from_text(c.long) == a, (name, c.long)
            assert "orange" in c.long and "walking towards you" in c.long and "narrow hallway" in c.long
            assert TOK.unknown_words(c.long) == [] and TOK.unknown_words(c.short) == []
            assert len(TOK.split(c.long)) + 2 <= captions.LONG_LEN and len(TOK.split(c.short)) + 2 <= captions.SHORT_LEN
    assert not captions.TemplateCaptioner().caption(None, None).ok


def test_parse_caption_reply():
    c = captions.parse_caption_reply('```json\n{"long": "People ahead. You should keep to the right.", "short": "people"}\n```')
    assert c.ok and c.short == "people" and captions.ACTIONS[c.action] == "keep_right"
    c = captions.parse_caption_reply("A busy hall. The robot should slow down and wait.")
    assert c.ok and captions.ACTIONS[c.action] == "yield" and c.short == "A busy hall"


def test_openai_captioner_fails_softly():
    cap = captions.OpenAICaptioner("http://127.0.0.1:9/v1", "m", timeout=0.5)
    c = cap.caption(np.zeros((8, 8, 3), np.float32))
    assert not c.ok
    with pytest.raises(ValueError):
        captions.OpenAICaptioner("ftp://x", "m")


def test_tokenizer():
    ids, mask = TOK.encode("A person in a red shirt, zyxwv!", 12)
    assert ids[0] == 1 and ids[mask.sum() - 1] == EOS and np.all(ids[~mask] == PAD)
    words = TOK.split("A person in a red shirt, zyxwv!")
    assert words[-1] == "zyxwv" and TOK.unknown_words("a zyxwv") == ["zyxwv"]
    # unknown words hash into the buckets, deterministically
    h = TOK.word_id("zyxwv")
    assert h == Tokenizer().word_id("zyxwv") and h >= 3 + len(TOK.words) and h < TOK.vocab_size
    ids, mask = TOK.encode(" ".join(["person"] * 50), 10)
    assert mask.all() and ids[-1] == EOS
    with pytest.raises(ValueError):
        TOK.encode("x", 2)
    with pytest.raises(TypeError):
        TOK.split(3)


def test_samples_from_a_short_episode(hallway):
    from types import SimpleNamespace

    # a synthetic "expert" record: the robot drives straight at 0.5 m/s, the people stand still
    T = 31
    robot = np.stack([np.arange(T) * 0.05, np.zeros(T), np.zeros(T)], -1).astype(np.float32)
    people = np.repeat(np.asarray(hallway.peds.pos)[None], T, 0)
    res = SimpleNamespace(robot=robot, people=people, dt=0.1)
    s = dataset.samples_from_episode(hallway, res, every=10, augment=1, rng=np.random.default_rng(0))
    assert len(s) >= 3
    assert s.image.shape[1:] == (render.IMG_H, render.IMG_W, 3) and s.image.dtype == np.uint8
    assert s.points.shape[1:] == (lidar.N_POINTS, 4) and s.future.shape[1:] == (features.HORIZON, 3)
    assert len(s.long) == len(s) == len(s.short)
    assert all(captions.action_from_text(t) == a for t, a in zip(s.long, s.action))
    assert s.future[0, 0, 0] == pytest.approx(0.05 * features.FUTURE_STRIDE, abs=1e-4)
    sub = s.subset([0, 1])
    assert len(sub) == 2 and sub.long == s.long[:2]


def test_with_action_rewrites_only_the_action():
    scene = captions.CaptionScene("a corridor", "d", 0, np.array([[2.0, 0.5]]), np.array([[-1.0, 0.0]]),
                            np.array([2]), np.array([-1]), (1.2, 1.3, 9.0), captions.ACTIONS.index("straight"))
    for v in (0, 1):
        c = captions.TemplateCaptioner().caption(None, scene, variant=v).long
        for a in range(len(captions.ACTIONS)):
            c2 = captions.with_action(c, a)
            assert captions.action_from_text(c2) == a
            # the description before the action is untouched
            assert c2.split("you should")[0] == c.split("you should")[0]
    assert captions.with_action("A busy hall. The robot should wait.", 0) is None


def test_extend_to_goal_continues_the_labels():
    poses = np.stack([np.arange(20) * 0.1, np.zeros(20), np.full(20, 0.1)], -1)
    goal = np.array([2.15, 0.0])
    ext = features.extend_to_goal(poses, goal)
    np.testing.assert_array_equal(ext[:20], poses)
    np.testing.assert_allclose(ext[-1, :2], goal)
    assert np.all(np.linalg.norm(np.diff(ext[19:, :2], axis=0), axis=1) <= 0.1 + 1e-9)
    assert np.all(ext[20:, 2] == 0.1)  # heading kept
    np.testing.assert_array_equal(features.extend_to_goal(poses, poses[-1, :2]), poses)


def test_labels_of_a_reached_episode_end_at_the_goal(hallway):
    from types import SimpleNamespace

    # the record stops 0.3 m short of the goal, as a reached episode does (goal tolerance)
    x_end = float(hallway.goal[0]) - 0.3
    robot = np.stack([np.linspace(x_end - 1.5, x_end, 16), np.zeros(16), np.zeros(16)], -1).astype(np.float32)
    people = np.repeat(np.asarray(hallway.peds.pos)[None], 16, 0)
    for reached, end in ((False, x_end), (True, float(hallway.goal[0]))):
        res = SimpleNamespace(robot=robot, people=people, dt=0.1, reached=reached)
        s = dataset.samples_from_episode(hallway, res, every=10, augment=0, rng=np.random.default_rng(0))
        last = s.future[-1, -1, 0] + robot[s.t[-1], 0]  # robot frame = world shifted (yaw 0)
        assert last == pytest.approx(end, abs=1e-3)


def test_expert_action_is_judged_from_the_state_not_the_robot(hallway):
    """The LLU's offline captioner labels a view with what the expert would do from there."""
    from splatsearch.social.convoi.runner import expert_rollout

    start = np.asarray(hallway.start, np.float32)
    zero = np.zeros(2, np.float32)
    poses = expert_rollout(hallway, start, zero, hallway.peds, 0, 8)
    assert poses.shape[1] == 3 and 2 <= len(poses) <= 9
    np.testing.assert_allclose(poses[0], start)
    assert poses[-1, 0] > start[0]  # it heads down the hallway toward the goal
    assert captions.ACTIONS[features.expert_action(hallway, start, zero, hallway.peds, 0, reference="expert")] == "straight"
    # the human-like reference (the default) moves into the right-hand lane of the hallway first
    assert captions.ACTIONS[features.expert_action(hallway, start, zero, hallway.peds, 0)] == "keep_right"
    # the same place faced the wrong way: the reference turns round, whatever a planner would do
    back = start + np.array([0.0, 0.0, np.pi], np.float32)
    for ref in ("expert", "human"):
        assert captions.ACTIONS[features.expert_action(hallway, back, zero, hallway.peds, 0, reference=ref)] in (
            "turn_left", "turn_right", "yield")
    with pytest.raises(ValueError):
        expert_rollout(hallway, start, zero, hallway.peds, 0, 0)
    with pytest.raises(ValueError, match="pose must be"):
        expert_rollout(hallway, start[:2], zero, hallway.peds, 0, 8)
    with pytest.raises(ValueError, match="t_index"):
        expert_rollout(hallway, start, zero, hallway.peds, -1, 8)


def test_training_scenes_sample_door_widths_and_never_the_held_out_doorway_seeds():
    from splatsearch.social.convoi.scenario_names import DOOR_TRAIN_SEEDS, LLU_ADAPT_SEEDS, LLU_TEST_SEEDS
    from splatsearch.social.convoi.scenarios import GEOMETRY, make_scenario, training_geometry
    from splatsearch.social.olivia.dataset import Samples
    from splatsearch.social.olivia.train import TrainConfig, assert_held_out

    tc = TrainConfig()
    assert tc.vary_geometry and tuple(tc.door_seeds) == DOOR_TRAIN_SEEDS
    held = set(LLU_ADAPT_SEEDS) | set(LLU_TEST_SEEDS)
    assert not held & set(tc.door_seeds) and not held & set(tc.train_seeds) and not held & set(tc.val_seeds)
    default, lo, hi = GEOMETRY["doorway"]["door_width"]
    widths = np.array([training_geometry("doorway", s)["door_width"] for s in range(200, 300)])
    assert widths.min() >= lo and widths.max() <= hi
    # across the range, the held-out door (default width) inside it
    assert widths.min() < default < widths.max() and np.ptp(widths) > 0.8 * (hi - lo)
    dw = [training_geometry("doorway", s)["door_width"] for s in tc.door_seeds]
    assert min(dw) < default + 0.1 and max(dw) > default + 0.25
    # the width is the scene's: the gap between the two door walls' ends
    scn = make_scenario("doorway", 200, door_width=1.4)
    caps = scn.capsules[-2:]
    assert caps[1, 1] - caps[0, 3] == pytest.approx(1.4, abs=1e-5)
    with pytest.raises(ValueError):
        make_scenario("doorway", 0, width=2.0)
    # the dataset check: a training set holding a held-out doorway seed is refused
    from splatsearch.social.convoi.scenarios import SCENARIOS

    def fake(scenario, seed):
        n = 2
        return Samples(np.zeros((n, 2, 2, 3), np.uint8), np.zeros((n, 3, 4), np.float32), np.ones((n, 3), bool),
                       np.zeros((n, 9), np.float32), np.zeros((n, 10, 3), np.float32), np.zeros(n, np.int32),
                       ["a"] * n, ["b"] * n, np.full(n, SCENARIOS.index(scenario), np.int32), np.full(n, seed, np.int32),
                       np.arange(n, dtype=np.int32))

    ok = Samples.concat([fake("hallway", 1000), fake("doorway", 200)])  # hallway 1000 is not the doorway's
    assert_held_out(ok, "doorway", sorted(held))
    with pytest.raises(ValueError, match="held-out"):
        assert_held_out(Samples.concat([ok, fake("doorway", 1003)]), "doorway", sorted(held))


def test_free_space_sees_the_passage_width():
    from splatsearch.social.convoi.scenarios import make_scenario

    narrow = make_scenario("hallway", 0, width=2.0)
    wide = make_scenario("hallway", 0, width=3.0)
    pose = np.array([3.0, 0.0, 0.0])
    fn, fw = features.free_space(narrow.field(), pose), features.free_space(wide.field(), pose)
    # left / right: (half width - robot radius) / range, within a ray step
    assert fn[0] == pytest.approx((1.0 - 0.05 - 0.25) / features.FREE_RANGE, abs=0.05)
    assert fw[0] == pytest.approx((1.5 - 0.05 - 0.25) / features.FREE_RANGE, abs=0.05)
    assert fn[1] < fw[1]
    g = features.goal_features(narrow.global_path(), narrow.goal, pose, narrow.field())
    assert g.shape == (features.GOAL_DIM,) and np.allclose(g[5:], fn)


def test_headon_training_doorways_cover_the_width_range_and_avoid_held_out_seeds():
    from splatsearch.social.convoi.scenario_names import DOOR_TRAIN_SEEDS, LLU_ADAPT_SEEDS, LLU_TEST_SEEDS
    from splatsearch.social.convoi.scenarios import GEOMETRY
    from splatsearch.social.olivia.dataset import HEADON_DELAY, HEADON_DOOR_SEEDS, build_dataset, headon_doorway
    from splatsearch.social.olivia.train import TrainConfig

    tc = TrainConfig()
    assert tuple(tc.headon_door_seeds) == HEADON_DOOR_SEEDS and len(HEADON_DOOR_SEEDS) >= 10
    held = set(LLU_ADAPT_SEEDS) | set(LLU_TEST_SEEDS)
    assert not held & set(HEADON_DOOR_SEEDS) and not set(DOOR_TRAIN_SEEDS) & set(HEADON_DOOR_SEEDS)
    default, lo, hi = GEOMETRY["doorway"]["door_width"]
    scenes = [headon_doorway(s) for s in HEADON_DOOR_SEEDS]
    widths = np.array([s._cache["geometry"]["door_width"] for s in scenes])
    delays = np.array([s._cache["geometry"]["headon_delay"] for s in scenes])
    assert widths.min() >= lo and widths.max() <= hi and widths.min() < default < widths.max()
    assert np.all((delays >= HEADON_DELAY[0]) & (delays <= HEADON_DELAY[1]))
    for s, w in zip(HEADON_DOOR_SEEDS, widths):
        plain = make_scenario("doorway", s, door_width=float(w))
        h = headon_doorway(s)
        # same walls and goals; only the person starts further back along its way to the door
        np.testing.assert_array_equal(np.asarray(h.capsules), np.asarray(plain.capsules))
        np.testing.assert_array_equal(np.asarray(h.peds.goals), np.asarray(plain.peds.goals))
        p0, p1, g = np.asarray(plain.peds.pos[0]), np.asarray(h.peds.pos[0]), np.asarray(plain.peds.goals[0, 0])
        back = np.linalg.norm(p1 - g) - np.linalg.norm(p0 - g)
        assert back == pytest.approx(float(plain.peds.v0[0]) * h._cache["geometry"]["headon_delay"], abs=1e-4)
    with pytest.raises(ValueError, match="delay"):
        headon_doorway(220, delay=-1.0)
    with pytest.raises(ValueError, match="doorways only"):
        build_dataset(("hallway",), (0,), headon=True)


@pytest.mark.slow
def test_reference_walker_steps_aside_on_a_headon_training_doorway():
    from splatsearch.social.convoi.runner import REFERENCE, run_episode
    from splatsearch.social.olivia.dataset import headon_doorway

    scn = headon_doorway(210, delay=1.4)
    res = run_episode(scn, REFERENCE)
    xy = np.asarray(res.robot)[:, :2]
    before_door = (xy[:, 0] > 1.0) & (xy[:, 0] < 5.0)
    assert res.reached
    # it yields: a sidestep of more than 1 m to its right before the door, then through the door
    assert (xy[before_door, 1] - scn.start[1]).min() < -1.0
    plain = run_episode(make_scenario("doorway", 210, door_width=scn._cache["geometry"]["door_width"]), REFERENCE)
    pxy = np.asarray(plain.robot)[:, :2]
    assert (pxy[(pxy[:, 0] > 1.0) & (pxy[:, 0] < 5.0), 1] - scn.start[1]).min() > -0.5


def test_social_data_builds_the_doorways_social_train_builds(tmp_path, monkeypatch):
    """`social data` with its defaults builds the training split social train builds: the four
    scenarios, then the doorways (sampled widths), then the head-on doorways, in that order."""
    import argparse

    from splatsearch.social.olivia import cli, train
    from splatsearch.social.olivia.dataset import HEADON_DOOR_SEEDS, Samples

    calls = []

    def fake(scenarios, seeds, *, every=4, augment=1, progress=None, vary_geometry=False, headon=False,
             perceived_berth=0.0, **_):
        rows = [(SCEN.index(n), int(s), int(headon)) for n in scenarios for s in seeds]
        calls.append((tuple(scenarios), tuple(seeds), vary_geometry, headon, perceived_berth))
        n = len(rows)
        for i in range(n):
            if progress is not None:
                progress(i + 1, n, "x")
        return Samples(np.zeros((n, 1, 1, 3), np.uint8), np.zeros((n, 1, 4), np.float32), np.ones((n, 1), bool),
                       np.zeros((n, 2), np.float32), np.zeros((n, 1, 3), np.float32), np.zeros(n, np.int32),
                       ["a"] * n, ["b"] * n, np.asarray([r[0] for r in rows], np.int32),
                       np.asarray([r[1] for r in rows], np.int32), np.asarray([r[2] for r in rows], np.int32))

    from splatsearch.social.convoi.scenario_names import SCENARIOS as SCEN

    monkeypatch.setattr(dataset, "build_dataset", fake)
    monkeypatch.setattr(train, "build_dataset", fake)
    parser = argparse.ArgumentParser()
    cli.register_olivia(parser.add_subparsers(dest="cmd"))
    args = parser.parse_args(["data", "--out", str(tmp_path / "data"), "--workers", "1", "--no-progress"])
    assert args.headon_door_seeds == HEADON_DOOR_SEEDS
    assert args.func(args) == 0
    got = Samples.load(str(tmp_path / "data" / "samples_train.npz"))
    assert all(c[2] for c in calls)  # sampled geometry everywhere
    assert {c[4] for c in calls} == {train.TrainConfig().perceived_berth}  # the goal features' route

    class Stop(Exception):
        pass

    def stop(*a, **k):
        raise Stop

    monkeypatch.setattr(train, "assert_held_out", stop)
    with pytest.raises(Stop):
        train.train_olivia(str(tmp_path / "train"), train.TrainConfig())
    want = Samples.load(str(tmp_path / "train" / "samples_train.npz"))
    for k in ("scenario", "seed", "t"):
        np.testing.assert_array_equal(getattr(got, k), getattr(want, k))
    headon = got.t == 1
    assert set(got.seed[headon]) == set(HEADON_DOOR_SEEDS)
    door = (got.scenario == SCEN.index("doorway")) & ~headon
    assert set(got.seed[door]) == set(train.TrainConfig().door_seeds)
    # 'none' leaves them out; held-out seeds are refused
    args = parser.parse_args(["data", "--out", str(tmp_path / "d2"), "--workers", "1", "--no-progress",
                              "--door-seeds", "none", "--headon-door-seeds", "none"])
    assert args.func(args) == 0
    assert not np.any(Samples.load(str(tmp_path / "d2" / "samples_train.npz")).scenario == SCEN.index("doorway"))
    args = parser.parse_args(["data", "--out", str(tmp_path / "d3"), "--workers", "1", "--headon-door-seeds", "505"])
    with pytest.raises(SystemExit, match="held-out"):
        args.func(args)


def test_training_goal_features_follow_the_perceived_route():
    """The samples' goal route is the one the planner reads at run time: walls-only until the
    second sweep, then around the standing groups the robot sees (berth 0: walls-only throughout)."""
    from types import SimpleNamespace

    from splatsearch.social.convoi.scenarios import make_scenario
    from splatsearch.social.olivia.dataset import perceived_paths
    from splatsearch.social.olivia.lidar import PREV_STEPS

    scn = make_scenario("static_groups", 0)
    T = 12
    poses = np.stack([np.asarray(scn.start, np.float32)] * (T + 1))
    poses[:, 0] += 0.05 * np.arange(T + 1)
    people = np.repeat(np.asarray(scn.peds.pos, np.float32)[None], T + 1, 0)  # everyone still
    res = SimpleNamespace(robot=poses, people=people)
    walls = scn.global_path()
    for p in perceived_paths(scn, res, 0.0):
        np.testing.assert_array_equal(p, walls)
    paths = perceived_paths(scn, res, 0.8)
    assert len(paths) == T + 1
    np.testing.assert_array_equal(paths[0], walls)  # no second sweep yet: nobody is classed
    after = paths[PREV_STEPS]
    assert after.shape != walls.shape or not np.allclose(after, walls)
    stand = np.asarray(scn.peds.pos)[scn.standing_people()]
    gap = np.linalg.norm(after[:, None] - stand[None], axis=-1).min()
    assert gap > 0.8  # around the standing people, never through a group
    assert np.linalg.norm(walls[:, None] - stand[None], axis=-1).min() < 0.8
