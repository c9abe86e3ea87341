"""OLiVia-Nav training pieces: a tiny training run, LLU, checkpoints, CLI wiring (fast)."""

import argparse
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from splatsearch.social.olivia import train as ot
from splatsearch.social.olivia import sc_clip
from splatsearch.social.olivia.llu import LLUConfig, TextDB, add_view_entries, build_text_db, llu_update
from splatsearch.social.olivia.render import IMG_H, IMG_W
from splatsearch.social.olivia.tokenizer import DEFAULT_TOKENIZER as TOK

TINY = sc_clip.SCCLIPConfig(width=32, depth=1, heads=2, mlp=64, text_width=32, text_depth=1, text_heads=2,
                            text_mlp=64, embed=16, pce_k=4, text_len=40)
CAPTIONS = ["a person in a red shirt ahead you should keep to the right",
            "the space is open you should continue straight",
            "a wall is ahead you should turn left",
            "people standing in a group you should slow down and yield",
            "a person in a blue shirt walking away you should keep to the left",
            "narrow hallway with walls on both sides continue straight",
            "a person in a green shirt crossing your path you should yield",
            "a corner ahead you should turn right"]


def _pairs():
    # images whose colour encodes the caption index, so the pairs are learnable
    rng = np.random.default_rng(0)
    imgs = np.zeros((8, IMG_H, IMG_W, 3), np.uint8)
    for i in range(8):
        imgs[i] = (np.array([i & 1, (i >> 1) & 1, (i >> 2) & 1]) * 200 + 30).astype(np.uint8)
        imgs[i] += rng.integers(0, 20, imgs[i].shape, dtype=np.uint8)
    return imgs


@pytest.fixture(scope="module")
def tiny_params():
    return sc_clip.init_sc_clip(jax.random.PRNGKey(0), TINY)


@pytest.mark.slow  # about a minute of XLA compilation on 2 cores; the LLU update test trains by default
def test_tiny_sc_clip_training_lowers_the_loss(tiny_params):
    imgs = _pairs()
    li, lm = TOK.encode_batch(CAPTIONS, 32)
    si, sm = TOK.encode_batch([c.split(" you ")[0] for c in CAPTIONS], 16)
    batch = {"image": imgs, "long_ids": li, "long_mask": lm, "short_ids": si, "short_mask": sm}
    loss = sc_clip.make_loss_fn(TINY)
    jb = {k: jnp.asarray(v) for k, v in batch.items()}
    before = float(jax.jit(loss)(tiny_params, jb))
    r = ot.fit(lambda p, b, k: loss(p, b), tiny_params, lambda rng: ot.batches(batch, 8, rng), [jb],
               lr=3e-3, weight_decay=0.0, epochs=15, patience=15)
    assert len(r.train) == 15 and not r.stopped_early
    assert min(r.val) < 0.5 * before
    assert r.val[r.best_epoch] == min(r.val)
    # the best params are the ones returned
    assert float(jax.jit(loss)(r.params, jb)) == pytest.approx(min(r.val), rel=1e-4)


def test_fit_stops_early_when_validation_stalls(tiny_params):
    calls = []
    r = ot.fit(lambda p, b, k: jnp.sum(p["w"] ** 2) + 0 * b["x"].sum(), {"w": jnp.ones(3)},
               lambda rng: [{"x": jnp.zeros(1)}], [{"x": jnp.zeros(1)}], lr=0.0, weight_decay=0.0, epochs=50,
               patience=3, on_improve=lambda p, e: calls.append(e))
    assert r.stopped_early and len(r.val) == 4 and calls == [0]
    with pytest.raises(ValueError):
        ot.fit(lambda p, b, k: 0.0, {}, lambda rng: [], [], lr=1e-3, weight_decay=0, epochs=0, patience=1)


def test_llu_update_lowers_eq4_and_rebuilds_db(tiny_params):
    imgs = _pairs()
    cfg = LLUConfig(size=8, mu=0.1, steps=15, lr=3e-3, batch=8)
    new, losses = llu_update(tiny_params, imgs, CAPTIONS, cfg, TINY)
    assert len(losses) == 15 and losses[-1] < losses[0]
    db = build_text_db(new, CAPTIONS + CAPTIONS[:2], TINY)
    assert db.embeddings.shape == (8, 16) and len(db.captions) == 8  # duplicates dropped
    np.testing.assert_allclose(np.linalg.norm(db.embeddings, axis=1), 1, atol=1e-5)
    assert [int(a) for a in db.actions[:4]] == [1, 0, 3, 5]
    with pytest.raises(ValueError):
        llu_update(tiny_params, imgs[:1], CAPTIONS[:1], cfg, TINY)


def _toy_params():
    return {"tsm": {"Dense_0": {"kernel": jnp.arange(6.0).reshape(2, 3), "bias": jnp.zeros(3)}},
            "tpn": {"query": jnp.ones((1, 2, 4))}}


def test_checkpoint_round_trip(tmp_path):
    path = str(tmp_path / "c.npz")
    db = TextDB(np.eye(2, 4, dtype=np.float32), ["go straight", "keep right"], np.array([0, 1], np.int32))
    ot.save_checkpoint(path, _toy_params(), db=db, meta={"config": {}, "note": "x"})
    assert [f for f in os.listdir(tmp_path) if f.startswith(".ckpt-")] == []  # no temporary left behind
    params, db2, meta = ot.load_checkpoint(path)
    np.testing.assert_array_equal(np.asarray(params["tsm"]["Dense_0"]["kernel"]), np.arange(6.0).reshape(2, 3))
    assert params["tpn"]["query"].shape == (1, 2, 4)
    assert db2.captions == db.captions and np.array_equal(db2.embeddings, db.embeddings)
    assert db2.keys is None
    assert meta["note"] == "x"
    # an LLU update's view-keyed entries survive the round trip
    db3 = add_view_entries(db, np.ones((1, 4), np.float32), np.ones((1, 4), np.float32), ["you should yield"])
    ot.save_checkpoint(path, _toy_params(), db=db3, meta={"config": {}})
    _, db4, _ = ot.load_checkpoint(path)
    np.testing.assert_array_equal(db4.key_matrix, db3.key_matrix)
    assert db4.captions == db3.captions


def test_corrupt_checkpoints_are_rejected(tmp_path):
    path = str(tmp_path / "c.npz")
    ot.save_checkpoint(path, _toy_params())
    raw = open(path, "rb").read()
    # truncated
    open(tmp_path / "trunc.npz", "wb").write(raw[: len(raw) // 2])
    with pytest.raises(ot.CheckpointError):
        ot.load_checkpoint(str(tmp_path / "trunc.npz"))
    # not a zip at all
    open(tmp_path / "junk.npz", "wb").write(b"not a checkpoint")
    with pytest.raises(ot.CheckpointError):
        ot.load_checkpoint(str(tmp_path / "junk.npz"))
    # an array changed but the header kept: the digest catches it
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["p/tsm/Dense_0/kernel"] = arrays["p/tsm/Dense_0/kernel"] + 1
    np.savez(tmp_path / "tampered.npz", **arrays)
    with pytest.raises(ot.CheckpointError, match="integrity"):
        ot.load_checkpoint(str(tmp_path / "tampered.npz"))
    # a plain npz without our header
    np.savez(tmp_path / "foreign.npz", a=np.zeros(2))
    with pytest.raises(ot.CheckpointError, match="header"):
        ot.load_checkpoint(str(tmp_path / "foreign.npz"))
    with pytest.raises(ot.CheckpointError, match="no checkpoint"):
        ot.load_checkpoint(str(tmp_path / "missing.npz"))
    # a partial checkpoint is not a planner
    with pytest.raises(ot.CheckpointError, match="full"):
        ot.load_planner(path)


def test_register_olivia_adds_train_and_eval():
    from splatsearch.social.olivia.cli import cmd_eval, cmd_train, register_olivia

    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="cmd")
    register_olivia(sub)
    a = parser.parse_args(["train", "--train-seeds", "0-2", "--scenarios", "hallway,doorway", "--no-progress"])
    assert a.func is cmd_train and a.train_seeds == (0, 1, 2) and a.scenarios == ("hallway", "doorway")
    b = parser.parse_args(["eval", "--seeds", "1000,1003", "--checkpoint", "x.npz"])
    assert b.func is cmd_eval and b.seeds == (1000, 1003)
    with pytest.raises(SystemExit):
        parser.parse_args(["train", "--scenarios", "nowhere"])
    with pytest.raises(SystemExit):
        parser.parse_args(["eval", "--seeds", "a-b"])


@pytest.mark.slow
def test_closed_loop_episode_with_untrained_networks():
    from splatsearch.social.olivia import tpn
    from splatsearch.social.olivia import tsm
    from splatsearch.social.olivia.llu import LLUBuffer
    from splatsearch.social.olivia.planner import OliviaConfig, OliviaNav, run_olivia_episode
    from splatsearch.social.convoi.scenarios import make_scenario

    cfg = OliviaConfig()
    k = jax.random.split(jax.random.PRNGKey(0), 3)
    params = {"clip": sc_clip.init_sc_clip(k[0], cfg.clip), "tpn": tpn.init_tpn(k[1], cfg.tpn),
              "tsm": tsm.init_tsm(k[2], cfg.tsm)}
    db = build_text_db(params["clip"], CAPTIONS, cfg.clip)
    planner = OliviaNav(params, db, cfg)
    buf = LLUBuffer(3)
    res = run_olivia_episode(make_scenario("hallway", 1000), planner, max_steps=12, buffer=buf, buffer_every=1)
    assert res.robot.shape == (13, 3) and res.people.shape[0] == 13 and res.cmds.shape == (12, 2)
    assert buf.full and buf.images[0].shape == (IMG_H, IMG_W, 3)
    # the untrained planner's views are captioned with the expert's action from the same state
    from splatsearch.social.olivia.features import expert_action

    scn = make_scenario("hallway", 1000)
    assert buf.scenes[0].action == expert_action(scn, scn.start, np.zeros(2, np.float32), scn.peds, 0)
    assert res.plan_ms > 0
    with pytest.raises(ValueError):
        OliviaNav(params, db, cfg, variant="nope")


def _plans():
    t = np.linspace(0.1, 1.0, 10)
    z = 0 * t
    straight = np.stack([2.4 * t, z, z], -1)
    left = np.stack([2.2 * t, 0.6 * t, z], -1)
    right = np.stack([2.2 * t, -0.6 * t, z], -1)
    return np.stack([straight, left, right]).astype(np.float32)


def test_tsm_rows_add_counterfactual_captions():
    from splatsearch.social.olivia.captions import ACTIONS, CaptionScene, TemplateCaptioner, action_from_text

    scene = CaptionScene("a corridor", "d", 0, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, int),
                         np.zeros(0, int), (1.2, 1.3, 9.0), ACTIONS.index("straight"))
    caption = TemplateCaptioner().caption(None, scene).long
    plans = _plans()
    s = _Rows([caption, "free text from a VLM: keep right"], plans[[0, 2]],
              np.array([ACTIONS.index("straight"), ACTIONS.index("keep_right")]))
    caps, idx, ks, fact = ot.tsm_rows(np.stack([plans, plans]), s)
    # sample 0: its own caption, then one rewritten caption per other action its plans perform;
    # sample 1 (free text) cannot be rewritten
    assert idx.tolist() == [0, 0, 0, 1] and fact.tolist() == [True, False, False, True]
    expected = [ACTIONS.index(a) for a in ("straight", "keep_right", "keep_left")]
    assert [action_from_text(c) for c in caps[:3]] == expected
    assert ks.tolist() == [0, 2, 1, 2]  # the plan performing each caption's action
    caps, idx, ks, fact = ot.tsm_rows(np.stack([plans, plans]), s, counterfactual=False)
    assert fact.all() and idx.tolist() == [0, 1]


class _Rows:
    """The fields of Samples that tsm_rows reads."""

    def __init__(self, long, future, action):
        self.long, self.future, self.action = long, future, action

    def __len__(self):
        return len(self.long)


def test_map_rows_pads_to_one_shape_and_val_batches():
    shapes = []

    def f(x):
        shapes.append(x.shape)
        return x * 2

    out = ot.map_rows(f, [np.arange(10.0)], 4)
    np.testing.assert_array_equal(out, np.arange(10.0) * 2)
    assert set(shapes) == {(4,)}
    vb = ot.val_batches({"x": np.arange(1100)}, 512)
    assert [len(b["x"]) for b in vb] == [367] * 3
    assert set(np.concatenate([np.asarray(b["x"]) for b in vb]).tolist()) == set(range(1100))
    assert [len(b["x"]) for b in ot.val_batches({"x": np.arange(300)}, 512)] == [300]


def test_cli_defaults_match_train_config():
    from splatsearch.social.olivia.cli import register_olivia

    parser = argparse.ArgumentParser()
    register_olivia(parser.add_subparsers(dest="cmd"))
    a = parser.parse_args(["train"])
    tc = ot.TrainConfig()
    for name in ("clip_epochs", "tpn_epochs", "tsm_epochs", "patience", "every", "augment"):
        assert getattr(a, name) == getattr(tc, name), name
    assert a.train_seeds == tc.train_seeds and a.val_seeds == tc.val_seeds


def test_fill_buffer_drives_episodes_until_full(monkeypatch):
    driven = []

    def fake_episode(scn, planner, *, buffer, buffer_every, **kw):
        driven.append(scn.seed)
        for _ in range(22):  # a short episode stores fewer views than |B|
            buffer.add(np.zeros((IMG_H, IMG_W, 3), np.float32))

    monkeypatch.setattr(ot, "run_olivia_episode", fake_episode)
    buf, used = ot.fill_buffer(None, "doorway", (500, 501, 502, 503), 50)
    assert buf.full and len(buf.images) == 50 and used == [500, 501, 502] and driven == used
    with pytest.raises(RuntimeError, match="22 of"):
        ot.fill_buffer(None, "doorway", (500,), 50)


@pytest.mark.slow  # two small TSM trainings (XLA compilation dominates)
def test_counterfactual_rows_make_the_tsm_select_by_the_caption():
    from splatsearch.social.olivia import tsm
    from splatsearch.social.olivia.captions import ACTIONS, CaptionScene, TemplateCaptioner, action_from_text

    rng = np.random.default_rng(0)
    plans = _plans()
    n = 48
    order = np.stack([rng.permutation(3) for _ in range(n)])  # the heads come in any order
    trajs = plans[order] + rng.normal(0, 0.02, (n, 3, 10, 3)).astype(np.float32)
    scene = CaptionScene("a corridor", "d", 0, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, int),
                         np.zeros(0, int), (1.2, 1.3, 9.0), ACTIONS.index("straight"))
    caption = TemplateCaptioner().caption(None, scene).long
    # the expert always drives straight, so every real caption says "straight"
    s = _Rows([caption] * n, plans[np.zeros(n, int)], np.full(n, ACTIONS.index("straight")))
    codes = np.eye(len(ACTIONS), 16, dtype=np.float32)  # a stand-in F_T that encodes the action

    def train(counterfactual):
        caps, idx, ks, fact = ot.tsm_rows(trajs, s, counterfactual)
        rows = {"e_text": codes[[action_from_text(c) for c in caps]], "trajs": trajs[idx], "k_star": ks,
                "factual": fact}
        cfg = tsm.TSMConfig(embed=16, width=32, K=3)
        r = ot.fit(tsm.make_loss_fn(cfg), tsm.init_tsm(jax.random.PRNGKey(0), cfg),
                   lambda g: ot.batches(rows, 32, g), ot.val_batches(rows, 512), lr=3e-3, weight_decay=0.0,
                   epochs=40, patience=40)
        return jax.jit(lambda e, t: tsm.TSM(cfg).apply({"params": r.params}, e, t, jnp.ones(len(t), bool)))

    left = codes[np.full(n, ACTIONS.index("keep_left"))]
    want = np.argmax(order == 1, 1)  # where the left plan is
    f = train(True)
    assert np.mean(np.argmax(np.asarray(f(jnp.asarray(left), jnp.asarray(trajs))), 1) == want) > 0.9
    assert np.mean(np.argmax(np.asarray(f(jnp.asarray(codes[np.zeros(n, int)]), jnp.asarray(trajs))), 1)
                   == np.argmax(order == 0, 1)) > 0.9
    # trained on the real captions alone, it picks the straight plan whatever the caption says
    g = train(False)
    assert np.mean(np.argmax(np.asarray(g(jnp.asarray(left), jnp.asarray(trajs))), 1) == want) < 0.2


@pytest.mark.slow
def test_after_an_update_the_tpn_keeps_its_encoder_and_view_entries_pass_the_gate():
    from splatsearch.social.olivia import tpn
    from splatsearch.social.olivia import tsm
    from splatsearch.social.olivia.features import GOAL_DIM
    from splatsearch.social.olivia.lidar import N_POINTS
    from splatsearch.social.olivia.planner import OliviaConfig, OliviaNav

    cfg = OliviaConfig()
    k = jax.random.split(jax.random.PRNGKey(0), 4)
    params = {"clip": sc_clip.init_sc_clip(k[0], cfg.clip), "tpn": tpn.init_tpn(k[1], cfg.tpn),
              "tsm": tsm.init_tsm(k[2], cfg.tsm)}
    db = build_text_db(params["clip"], CAPTIONS, cfg.clip)
    rng = np.random.default_rng(0)
    obs = (rng.integers(0, 255, (IMG_H, IMG_W, 3)).astype(np.uint8), rng.normal(size=(N_POINTS, 4)).astype(np.float32),
           np.ones(N_POINTS, bool), rng.normal(size=GOAL_DIM).astype(np.float32))
    before = OliviaNav(params, db, cfg).plan(*obs)
    moved = sc_clip.init_sc_clip(k[3], cfg.clip)  # stands in for the LLU-updated encoders
    same_tpn = OliviaNav(dict(params, clip=moved, clip_tpn=params["clip"]), db, cfg).plan(*obs)
    np.testing.assert_allclose(same_tpn.trajs, before.trajs, rtol=1e-5, atol=1e-5)
    assert not np.allclose(OliviaNav(dict(params, clip=moved), db, cfg).plan(*obs).trajs, before.trajs, atol=1e-5)
    # a view-keyed entry for this very view is retrieved at similarity ~1 and opens the gate
    e_i = ot.encode_all_images(moved, obs[0][None], cfg.clip)
    dbv = add_view_entries(db, e_i, ot.encode_all_texts(moved, ["you should yield"], cfg.clip), ["you should yield"])
    r = OliviaNav(dict(params, clip=moved, clip_tpn=params["clip"]), dbv, cfg).plan(*obs)
    assert r.caption == "you should yield" and r.similarity > cfg.view_gate


def test_llu_config_refuses_an_unknown_tpn_encoder():
    with pytest.raises(ValueError):
        LLUConfig(tpn_encoder="both")


@pytest.mark.slow
def test_an_update_with_the_updated_tpn_encoder_changes_the_plans():
    """tpn_encoder "updated" (the thesis: F_I^(i_t) feeds the TPN): no ``clip_tpn`` is kept, so the
    update moves the TPN's plans; the default keeps them."""
    from splatsearch.social.olivia import tpn
    from splatsearch.social.olivia import tsm
    from splatsearch.social.olivia.features import GOAL_DIM
    from splatsearch.social.olivia.lidar import N_POINTS
    from splatsearch.social.olivia.llu import LLUBuffer
    from splatsearch.social.olivia.planner import OliviaConfig, OliviaNav

    cfg = OliviaConfig()
    k = jax.random.split(jax.random.PRNGKey(1), 3)
    params = {"clip": sc_clip.init_sc_clip(k[0], cfg.clip), "tpn": tpn.init_tpn(k[1], cfg.tpn),
              "tsm": tsm.init_tsm(k[2], cfg.tsm)}
    planner = OliviaNav(params, build_text_db(params["clip"], CAPTIONS, cfg.clip), cfg)
    rng = np.random.default_rng(1)
    buf = LLUBuffer(4)
    for _ in range(4):
        buf.add(rng.integers(0, 255, (IMG_H, IMG_W, 3)).astype(np.uint8))
    obs = (buf.images[0], rng.normal(size=(N_POINTS, 4)).astype(np.float32), np.ones(N_POINTS, bool),
           rng.normal(size=GOAL_DIM).astype(np.float32))
    before = planner.plan(*obs).trajs
    small = dict(size=4, steps=3, batch=4, lr=1e-3)
    kept, _ = ot.apply_llu(planner, buf, CAPTIONS[:4], LLUConfig(**small))
    moved, _ = ot.apply_llu(planner, buf, CAPTIONS[:4], LLUConfig(**small, tpn_encoder="updated"))
    assert "clip_tpn" in kept.params and "clip_tpn" not in moved.params
    np.testing.assert_allclose(kept.plan(*obs).trajs, before, rtol=1e-5, atol=1e-5)
    assert not np.allclose(moved.plan(*obs).trajs, before, atol=1e-5)


def _drift_left(dy: float) -> np.ndarray:
    """A hand-made 4 s buffer future (HORIZON, 3), robot frame: 2 m ahead, ending ``dy`` m left."""
    from splatsearch.social.olivia.features import HORIZON

    f = np.linspace(0.0, 1.0, HORIZON + 1)[1:]
    x, y = 2.0 * f, dy * f ** 2
    return np.stack([x, y, np.arctan2(np.gradient(y), np.gradient(x))], -1)


def test_llu_caption_keep_captions_a_small_left_drift_keep_left():
    """LLUConfig.caption_keep: a 0.2 m left drift over 4 s is "keep left" for the buffer under the
    option, "straight" at the default (the training data's 0.35 m, unchanged)."""
    from splatsearch.social.olivia.captions import ACTIONS
    from splatsearch.social.olivia.features import KEEP_THRESHOLD, action_of

    traj = _drift_left(0.2)
    assert LLUConfig().caption_keep == KEEP_THRESHOLD == 0.35
    assert ACTIONS[action_of(traj, LLUConfig().caption_keep)] == "straight"
    assert ACTIONS[action_of(traj)] == "straight"
    assert ACTIONS[action_of(traj, LLUConfig(caption_keep=0.15).caption_keep)] == "keep_left"
    assert ACTIONS[action_of(_drift_left(-0.2), 0.15)] == "keep_right"
    with pytest.raises(ValueError):
        LLUConfig(caption_keep=0.0)


def test_fill_buffer_passes_caption_keep_to_the_buffer_episodes(monkeypatch):
    """Only the buffer's episodes get the threshold (None: not passed, the episode's default)."""
    from types import SimpleNamespace

    from splatsearch.social.olivia.llu import LLUBuffer

    got = []

    def episode(scn, planner, buffer=None, buffer_every=2, reference_shift=None, **kw):
        got.append(kw.get("caption_keep", "default"))
        for _ in range(2):
            buffer.add(np.zeros((IMG_H, IMG_W, 3), np.uint8))

    monkeypatch.setattr(ot, "run_olivia_episode", episode)
    monkeypatch.setattr(ot, "make_scenario", lambda name, seed: SimpleNamespace(seed=seed))
    buf, used = ot.fill_buffer(None, "doorway", [1, 2, 3], 4, caption_keep=0.2, carry_shift=False)
    assert isinstance(buf, LLUBuffer) and buf.full and used == [1, 2] and got == [0.2, 0.2]
    ot.fill_buffer(None, "doorway", [1, 2], 4, carry_shift=False)
    assert got[2:] == ["default", "default"]
