"""OLiVia-Nav networks and losses: shapes, masking, eq 2, eq 3, eq 4, eq 7 (fast)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from splatsearch.social.olivia import llu
from splatsearch.social.olivia import sc_clip
from splatsearch.social.olivia import tpn
from splatsearch.social.olivia import tsm
from splatsearch.social.olivia.captions import ACTIONS
from splatsearch.social.olivia.features import GOAL_DIM, HORIZON
from splatsearch.social.olivia.lidar import N_POINTS
from splatsearch.social.olivia.render import IMG_H, IMG_W
from splatsearch.social.olivia.tokenizer import DEFAULT_TOKENIZER as TOK

F32 = jnp.float32
SMALL_CLIP = sc_clip.SCCLIPConfig(width=32, depth=1, heads=2, mlp=64, text_width=32, text_depth=1, text_heads=2,
                                  text_mlp=64, embed=16, pce_k=4, text_len=40)
SMALL_TPN = tpn.TPNConfig(C=32, heads=8, K=3, channels=(8, 8, 8, 8, 8), vfe=8, gru=16, embed=16)


def _np_log_softmax(x, axis):
    x = x - x.max(axis, keepdims=True)
    return x - np.log(np.exp(x).sum(axis, keepdims=True))


# -- eq 3 ------------------------------------------------------------------------------------------

def test_contrastive_ce_matches_hand_computation():
    a = np.array([[1.0, 0.0], [0.0, 1.0], [0.6, 0.8]], np.float32)
    b = np.array([[0.8, 0.6], [0.0, 1.0], [1.0, 0.0]], np.float32)
    scale = 3.0
    logits = scale * a @ b.T  # rows already unit length
    i2t = -np.mean(np.diag(_np_log_softmax(logits, 1)))
    t2i = -np.mean(np.diag(_np_log_softmax(logits.T, 1)))
    got = float(sc_clip.contrastive_ce(jnp.asarray(a), jnp.asarray(b), scale, symmetric=False))
    assert got == pytest.approx(i2t, rel=1e-5)
    got = float(sc_clip.contrastive_ce(jnp.asarray(a), jnp.asarray(b), scale))
    assert got == pytest.approx(0.5 * (i2t + t2i), rel=1e-5)


def test_sc_clip_loss_aligned_is_low_and_shuffled_is_high():
    e = np.eye(4, 8, dtype=np.float32) * 3.0  # not unit: the loss normalises
    ls = jnp.asarray(np.log(50.0), F32)
    good = float(sc_clip.sc_clip_loss(jnp.asarray(e), jnp.asarray(e), jnp.asarray(e), ls, pce_k=4))
    bad = float(sc_clip.sc_clip_loss(jnp.asarray(e), jnp.asarray(e[::-1]), jnp.asarray(e[::-1]), ls, pce_k=4))
    assert good < 0.01
    assert bad > 10.0


def test_soft_targets_share_duplicates():
    ids = jnp.asarray([[1, 5, 2], [1, 5, 2], [1, 6, 2]])
    t = np.asarray(sc_clip.soft_targets(ids))
    np.testing.assert_allclose(t, [[0.5, 0.5, 0], [0.5, 0.5, 0], [0, 0, 1]])


def test_pce_keeps_top_components():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(12, 6)).astype(np.float32)
    np.testing.assert_allclose(np.asarray(sc_clip.pce(jnp.asarray(x), 6)), x, atol=1e-4)
    # rank-1 data (plus the mean) is reconstructed exactly by one component
    u = rng.normal(size=(12, 1)) * rng.normal(size=(1, 6)) + 2.0
    np.testing.assert_allclose(np.asarray(sc_clip.pce(jnp.asarray(u, F32), 1)), u, atol=1e-4)
    r = np.asarray(sc_clip.pce(jnp.asarray(x), 2))
    assert np.linalg.matrix_rank(r - r.mean(0), tol=1e-4) == 2


# -- eq 4 ------------------------------------------------------------------------------------------

def test_llu_loss_matches_eq4_by_hand():
    e_i = np.array([[1.0, 0.0], [0.0, 2.0]], np.float32)
    e_t = np.array([[1.0, 0.0], [0.6, 0.8]], np.float32)
    mu = 0.5
    # cosine similarities: [[1, 0.6], [0, 0.8]]
    s = np.array([[1.0, 0.6], [0.0, 0.8]]) / mu
    i2t = -np.mean([s[0, 0] - np.log(np.exp(s[0]).sum()), s[1, 1] - np.log(np.exp(s[1]).sum())])
    t2i = -np.mean([s[0, 0] - np.log(np.exp(s[:, 0]).sum()), s[1, 1] - np.log(np.exp(s[:, 1]).sum())])
    assert float(llu.llu_loss(jnp.asarray(e_i), jnp.asarray(e_t), mu, symmetric=False)) == pytest.approx(i2t, rel=1e-5)
    assert float(llu.llu_loss(jnp.asarray(e_i), jnp.asarray(e_t), mu)) == pytest.approx(0.5 * (i2t + t2i), rel=1e-5)
    # a lower temperature sharpens: the matched pairs dominate more
    assert float(llu.llu_loss(jnp.asarray(e_i), jnp.asarray(e_t), 0.1)) < float(llu.llu_loss(jnp.asarray(e_i), jnp.asarray(e_t), 1.0))
    with pytest.raises(ValueError, match="temperature"):
        llu.llu_loss(jnp.asarray(e_i), jnp.asarray(e_t), 0.0)


def test_text_db_retrieves_by_cosine():
    db = llu.TextDB(np.eye(3, dtype=np.float32), ["a", "b", "c"], np.array([0, 1, 2]))
    i, e = db.retrieve(np.array([0.1, 0.2, 5.0]))
    assert i == 2 and np.allclose(e, [0, 0, 1])


def test_view_entries_are_retrieved_by_their_view_and_give_their_caption():
    db = llu.TextDB(np.eye(3, dtype=np.float32), ["go straight", "keep to the right", "keep to the left"],
                    np.array([0, 1, 2], np.int32))
    view = np.array([0.6, 0.0, 0.8], np.float32)  # a view whose E_I is far from every caption's E_T
    text = np.array([[0.0, 0.0, 2.0]], np.float32)  # its caption says keep left
    db2 = llu.add_view_entries(db, view[None], text, ["you should yield"])
    assert len(db2.captions) == 4 and db2.actions[-1] == ACTIONS.index("yield")
    np.testing.assert_allclose(db2.key_matrix[:3], db.embeddings)  # offline entries keep their text keys
    i, e = db2.retrieve(view)
    assert i == 3 and np.allclose(e, [0, 0, 1])  # found by the view, it hands over the caption's E_T
    with pytest.raises(ValueError):
        llu.add_view_entries(db, view[None], text, ["a", "b"])
    with pytest.raises(ValueError):
        llu.TextDB(np.eye(3, dtype=np.float32), ["a", "b"], np.array([0, 1, 2]))


# -- SC-CLIP encoders --------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def clip_params():
    return sc_clip.init_sc_clip(jax.random.PRNGKey(0), SMALL_CLIP)


_enc_img = jax.jit(lambda p, x: sc_clip.encode_images(p, x, SMALL_CLIP))
_enc_txt = jax.jit(lambda p, i, m: sc_clip.encode_texts(p, i, m, SMALL_CLIP))


def test_sc_clip_shapes_and_unit_norm(clip_params):
    img = jnp.asarray(np.random.default_rng(0).integers(0, 255, (3, IMG_H, IMG_W, 3)), jnp.uint8)
    e = _enc_img(clip_params, img)
    assert e.shape == (3, 16)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(e), axis=1), 1.0, atol=1e-5)
    # uint8 and the same image in [0, 1] floats give the same embedding
    e2 = _enc_img(clip_params, img.astype(F32) / 255.0)
    np.testing.assert_allclose(np.asarray(e), np.asarray(e2), atol=1e-5)


def test_text_encoder_ignores_padding(clip_params):
    text = "a person in a red shirt walking towards you"
    i1, m1 = TOK.encode(text, 16)
    i2, m2 = TOK.encode(text, 40)
    i3 = i2.copy()
    i3[~m2] = 77  # garbage in the padded slots must not matter either
    e = [_enc_txt(clip_params, jnp.asarray(i[None]), jnp.asarray(m[None])) for i, m in ((i1, m1), (i2, m2), (i3, m2))]
    np.testing.assert_allclose(np.asarray(e[0]), np.asarray(e[1]), atol=1e-5)
    np.testing.assert_allclose(np.asarray(e[1]), np.asarray(e[2]), atol=1e-5)
    other = _enc_txt(clip_params, *map(lambda a: jnp.asarray(a[None]), TOK.encode("open space", 16)))
    assert float(jnp.abs(other - e[0]).max()) > 1e-3


def test_config_validation():
    with pytest.raises(ValueError, match="divisible"):
        sc_clip.SCCLIPConfig(patch=7)
    with pytest.raises(ValueError, match="divisible"):
        tpn.TPNConfig(C=100, heads=32)
    with pytest.raises(ValueError, match="five residual"):
        tpn.TPNConfig(channels=(8, 8))


# -- TPN -------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def tpn_setup():
    params = tpn.init_tpn(jax.random.PRNGKey(1), SMALL_TPN)
    rng = np.random.default_rng(1)
    B = 2
    pts = rng.uniform([-2, -4, 0, 0], [6, 4, 2, 1], (B, N_POINTS, 4)).astype(np.float32)
    pts[..., 3] = np.round(pts[..., 3])
    inputs = (jnp.asarray(rng.normal(size=(B, 16)), F32), jnp.asarray(pts), jnp.ones((B, N_POINTS), bool),
              jnp.asarray(rng.normal(size=(B, GOAL_DIM)), F32))
    f = jax.jit(lambda p, e, pt, v, g, ui, ul: tpn.TPN(SMALL_TPN).apply({"params": p}, e, pt, v, g, ui, ul))
    return params, inputs, f


def test_tpn_shapes(tpn_setup):
    params, (e, pts, v, g), f = tpn_setup
    out = f(params, e, pts, v, g, jnp.ones(2, bool), jnp.ones(2, bool))
    assert out.shape == (2, SMALL_TPN.K, HORIZON, 3)
    assert np.all(np.isfinite(np.asarray(out)))
    # the full-size configuration follows the thesis: C = 128, 32 heads, K = 5, 10 poses
    c = tpn.TPNConfig()
    assert (c.C, c.heads, c.K, c.horizon, len(c.channels)) == (128, 32, 5, 10, 5)
    # float32 parameters and outputs also under x64 (conftest): a float64 plan made the TSM's GRU
    # scan carry change dtype in closed loop
    assert {str(x.dtype) for x in jax.tree_util.tree_leaves(params)} == {"float32"}
    assert out.dtype == jnp.float32


def test_tpn_modality_masks(tpn_setup):
    params, (e, pts, v, g), f = tpn_setup
    on, off = jnp.ones(2, bool), jnp.zeros(2, bool)
    e2 = e + 3.0
    pts2 = pts.at[..., :2].add(0.7)
    # w/o E_I: the image embedding has no influence; with it, it does
    np.testing.assert_allclose(np.asarray(f(params, e, pts, v, g, off, on)), np.asarray(f(params, e2, pts, v, g, off, on)),
                               atol=1e-5)
    assert float(jnp.abs(f(params, e, pts, v, g, on, on) - f(params, e2, pts, v, g, on, on)).max()) > 1e-4
    # w/o E_L: the points have no influence; with them, they do
    np.testing.assert_allclose(np.asarray(f(params, e, pts, v, g, on, off)), np.asarray(f(params, e, pts2, v, g, on, off)),
                               atol=1e-5)
    assert float(jnp.abs(f(params, e, pts, v, g, on, on) - f(params, e, pts2, v, g, on, on)).max()) > 1e-4
    # invalid points are ignored
    v_half = v.at[:, ::2].set(False)
    pts3 = pts.at[:, ::2, :2].add(2.0)
    np.testing.assert_allclose(np.asarray(f(params, e, pts, v_half, g, on, on)),
                               np.asarray(f(params, e, pts3, v_half, g, on, on)), atol=1e-5)
    # masking is per sample: sample 1 keeps its image
    mixed = jnp.asarray([False, True])
    d = np.abs(np.asarray(f(params, e, pts, v, g, mixed, on) - f(params, e2, pts, v, g, mixed, on)))
    assert d[0].max() < 1e-5 and d[1].max() > 1e-4


def test_pillar_index_dump_slot():
    c = tpn.TPNConfig()
    pts = jnp.asarray([[0.1, 0.1, 0, 0], [-5.0, 0, 0, 0], [1.0, 1.0, 0, 0], [5.9, 3.9, 0, 0]], F32)
    valid = jnp.asarray([True, True, False, True])
    idx = np.asarray(tpn.pillar_index(pts, valid, c))
    dump = c.bev * c.bev
    assert idx[1] == dump and idx[2] == dump  # outside the grid, invalid
    assert idx[0] == int((0.1 + 4) / 0.25) * c.bev + int((0.1 + 2) / 0.25)
    assert idx[3] == (c.bev - 1) * c.bev + (c.bev - 1)


def test_wta_loss_picks_the_closest_head():
    target = jnp.zeros((1, HORIZON, 3), F32)
    pred = jnp.stack([jnp.full((HORIZON, 3), 1.0), jnp.full((HORIZON, 3), 0.2), jnp.full((HORIZON, 3), -0.5)])[None]
    err = np.asarray(tpn.head_errors(pred, target, yaw_weight=0.3))[0]
    np.testing.assert_allclose(err, [2.3, 0.092, 0.575], rtol=1e-5)
    assert float(tpn.wta_loss(pred, target)) == pytest.approx(err.min(), rel=1e-5)
    assert tpn.closest_head(pred, target).tolist() == [1]
    g = np.asarray(jax.jit(jax.grad(lambda p: tpn.wta_loss(p, target)))(pred))[0]
    assert np.abs(g[1]).sum() > 0 and np.abs(g[0]).sum() == 0 and np.abs(g[2]).sum() == 0
    # relaxed WTA also moves the losers, a little
    g = np.asarray(jax.jit(jax.grad(lambda p: tpn.wta_loss(p, target, eps=0.05)))(pred))[0]
    assert np.abs(g[0]).sum() > 0 and np.abs(g[0]).sum() < np.abs(g[1]).sum() * 20


def test_wta_wraps_heading_error():
    target = jnp.zeros((1, HORIZON, 3), F32).at[..., 2].set(np.pi - 0.05)
    pred = jnp.zeros((1, 1, HORIZON, 3), F32).at[..., 2].set(-np.pi + 0.05)
    assert float(tpn.wta_loss(pred, target, yaw_weight=1.0)) == pytest.approx(0.01, rel=1e-3)


# -- TSM -------------------------------------------------------------------------------------------

def test_tsm_shapes_loss_and_text_mask():
    cfg = tsm.TSMConfig(embed=16, width=32, K=3)
    p = tsm.init_tsm(jax.random.PRNGKey(2), cfg)
    rng = np.random.default_rng(2)
    e = jnp.asarray(rng.normal(size=(4, 16)), F32)
    tr = jnp.asarray(rng.normal(size=(4, 3, HORIZON, 3)), F32)
    apply = jax.jit(lambda e, tr, u: tsm.TSM(cfg).apply({"params": p}, e, tr, u))
    logits = apply(e, tr, jnp.ones(4, bool))
    assert logits.shape == (4, 3)
    off = jnp.zeros(4, bool)
    np.testing.assert_allclose(np.asarray(apply(e, tr, off)), np.asarray(apply(e * 5 + 1, tr, off)), atol=1e-5)
    # eq 7 by hand
    k = jnp.asarray([0, 2, 1, 1])
    ref = -np.mean(_np_log_softmax(np.asarray(logits), 1)[np.arange(4), np.asarray(k)])
    assert float(tsm.tsm_loss(logits, k)) == pytest.approx(ref, rel=1e-5)


def test_best_index_follows_the_caption_action():
    t = np.linspace(0.1, 1.0, HORIZON)
    straight = np.stack([2.4 * t, 0 * t, 0 * t], -1)
    right = np.stack([2.2 * t, -0.6 * t, -0.1 * t], -1)
    stop = np.stack([0.3 * t, 0 * t, 0 * t], -1)
    trajs = np.stack([straight, right, stop])
    expert = straight + np.array([0, -0.2, 0])  # closest to "straight" but the caption says keep right
    assert tsm.best_index(trajs, expert, ACTIONS.index("keep_right")) == 1
    assert tsm.best_index(trajs, expert, ACTIONS.index("straight")) == 0
    assert tsm.best_index(trajs, expert, ACTIONS.index("yield")) == 2
    # no trajectory turns left: fall back to the closest
    assert tsm.best_index(trajs, expert, ACTIONS.index("turn_left")) == 0


def test_tsm_loss_never_drops_text_from_counterfactual_rows():
    cfg = tsm.TSMConfig(embed=16, width=32, K=3)
    p = tsm.init_tsm(jax.random.PRNGKey(3), cfg)
    rng = np.random.default_rng(3)
    batch = {"e_text": jnp.asarray(rng.normal(size=(4, 16)), F32),
             "trajs": jnp.asarray(rng.normal(size=(4, 3, HORIZON, 3)), F32), "k_star": jnp.asarray([0, 1, 2, 1])}
    apply = jax.jit(lambda u: tsm.TSM(cfg).apply({"params": p}, batch["e_text"], batch["trajs"], u))
    with_text, without = apply(jnp.ones(4, bool)), apply(jnp.zeros(4, bool))
    loss = jax.jit(tsm.make_loss_fn(cfg, p_drop_text=1.0))  # drop E_T wherever it may be dropped
    fact = jnp.asarray([True, False, True, False])
    got = float(loss(p, batch | {"factual": fact}, jax.random.PRNGKey(0)))
    logits = np.where(np.asarray(fact)[:, None], np.asarray(without), np.asarray(with_text))
    assert got == pytest.approx(float(tsm.tsm_loss(jnp.asarray(logits), batch["k_star"])), rel=1e-5)
    # with every row factual, every row loses E_T
    assert float(loss(p, batch | {"factual": jnp.ones(4, bool)}, jax.random.PRNGKey(0))) == pytest.approx(
        float(tsm.tsm_loss(without, batch["k_star"])), rel=1e-5)


def test_retrieve_votes_on_the_action():
    from splatsearch.social.olivia.planner import N_VOTES, retrieve

    # the nearest caption says "yield" (5), but the next three neighbours say "keep_left" (2)
    emb = np.array([[1.0, 0.0], [0.99, 0.14], [0.98, 0.2], [0.97, 0.24], [0.0, 1.0]], np.float32)
    emb /= np.linalg.norm(emb, axis=1, keepdims=True)
    db, acts = jnp.asarray(emb), jnp.asarray([5, 2, 2, 2, 0], jnp.int32)
    e = jnp.asarray([1.0, 0.0], F32)
    j, votes = retrieve(db, acts, e, 1, 0.05)
    assert int(j) == 0 and votes.shape == (N_VOTES,)
    j, votes = retrieve(db, acts, e, 4, 0.05)
    assert int(j) == 1 and int(jnp.argmax(votes)) == 2  # the most similar keep_left caption
    assert float(votes.sum()) == pytest.approx(1.0, rel=1e-5)


def test_retrieve_prior_votes_carry_the_action():
    from splatsearch.social.olivia.planner import N_VOTES, retrieve

    emb = np.array([[1.0, 0.0], [0.0, 1.0]], np.float32)
    db, acts = jnp.asarray(emb), jnp.asarray([5, 1], jnp.int32)
    e = jnp.asarray([1.0, 0.1], F32)
    j, votes = retrieve(db, acts, e, 1, 0.05)
    assert int(j) == 0  # alone, this view retrieves the "yield" caption
    prior = jnp.zeros(N_VOTES, F32).at[1].set(3.0)  # three earlier views voted keep_right
    j, votes = retrieve(db, acts, e, 1, 0.05, prior)
    assert int(j) == 1 and float(votes[1]) == pytest.approx(3.0) and float(votes[5]) == pytest.approx(1.0)


def test_tpn_score_loss_is_the_cross_entropy_against_the_closest_head():
    rng = np.random.default_rng(3)
    trajs = jnp.asarray(rng.normal(size=(2, SMALL_TPN.K, HORIZON, 3)), F32)
    scores = jnp.asarray(rng.normal(size=(2, SMALL_TPN.K)), F32)
    target = trajs[:, 1] + 0.01
    k = np.asarray(tpn.closest_head(trajs, target))
    assert k.tolist() == [1, 1]
    want = -np.mean(np.asarray(jax.nn.log_softmax(scores, -1))[np.arange(2), k])
    assert float(tpn.score_loss(scores, trajs, target)) == pytest.approx(want, rel=1e-5)


@pytest.mark.slow  # compiles the TPN twice more (with and without the score head), ~40 s on 2 cores
def test_tpn_mode_scores_and_a_checkpoint_without_the_head(tpn_setup):
    params, (e, pts, v, g), _ = tpn_setup
    on = jnp.ones(2, bool)
    trajs, scores = tpn.TPN(SMALL_TPN).apply({"params": params}, e, pts, v, g, on, on, with_scores=True)
    assert trajs.shape == (2, SMALL_TPN.K, HORIZON, 3) and scores.shape == (2, SMALL_TPN.K)
    assert scores.dtype == jnp.float32 and np.all(np.isfinite(np.asarray(scores)))
    # a checkpoint without the head (score=False) still plans, with flat scores
    c = tpn.TPNConfig(**{**SMALL_TPN.__dict__, "score": False})
    p0 = tpn.init_tpn(jax.random.PRNGKey(2), c)
    assert "score_ffn" not in p0
    _, s0 = tpn.TPN(c).apply({"params": p0}, e, pts, v, g, on, on, with_scores=True)
    assert np.all(np.asarray(s0) == 0)


def test_select_logits_adds_the_tpn_scores():
    from splatsearch.social.olivia.planner import select_logits

    tsm_l = jnp.asarray([[2.0, 2.0, -5.0]])  # the caption's action: plans 0 and 1 alike
    tpn_s = jnp.asarray([[0.0, 3.0, 9.0]])   # the TPN prefers plan 2, then 1
    assert int(jnp.argmax(select_logits(tsm_l, tpn_s, 0.0))) in (0, 1)
    assert int(jnp.argmax(select_logits(tsm_l, tpn_s, 0.3))) == 1  # the TPN breaks the tie
    assert int(jnp.argmax(select_logits(tsm_l, tpn_s, 5.0))) == 2  # and outweighs the TSM when trusted more


def test_consistency_cost_holds_to_the_followed_plan_but_not_to_a_stop():
    from splatsearch.social.olivia.planner import consistency_cost

    xs = 0.24 * np.arange(1, HORIZON + 1)  # 0.6 m/s, poses every 0.4 s
    left = np.stack([xs, 0.1 * xs], -1)
    right = np.stack([xs, -0.1 * xs], -1)
    prev = np.vstack([[0.0, 0.0], left])  # the followed plan went left
    c = consistency_cost(np.stack([left, right]), prev, 0.0)
    assert c[0] == pytest.approx(0.0, abs=1e-12) and c[1] > 0.05
    # read at the same instants 0.2 s later: a plan that keeps the pace costs little
    shifted = left + np.array([0.12, 0.012])
    assert consistency_cost(shifted[None], prev, 0.2)[0] < 3e-3  # (the last pose is held at its end)
    stop = np.zeros((HORIZON + 1, 2))
    assert np.all(consistency_cost(np.stack([left, right]), stop, 0.2) == 0)  # waiting commits to nothing
    assert np.all(consistency_cost(np.stack([left, right]), None, 0.2) == 0)


def test_safety_cost_penalises_the_plan_into_a_person():
    from splatsearch.social.olivia.planner import safety_cost

    xs = 0.24 * np.arange(1, HORIZON + 1)
    straight = np.stack([xs, 0 * xs], -1)
    aside = np.stack([xs, np.minimum(0.6 * xs, 1.5)], -1)
    # one person walking toward the robot along its line at 1 m/s, 3 m ahead
    c = safety_cost(np.stack([straight, aside]), np.array([[3.0, 0.0]]), np.array([[-1.0, 0.0]]), 0.45)
    assert c[0] > 0.5 and c[1] < 0.25 * c[0]
    assert np.all(safety_cost(np.stack([straight, aside]), np.zeros((0, 2)), np.zeros((0, 2)), 0.45) == 0)


def test_side_cost_asks_to_pass_head_on_people_on_their_left():
    from splatsearch.social.olivia.planner import side_cost

    xs = 0.24 * np.arange(1, HORIZON + 1)
    right = np.stack([xs, -np.minimum(0.6 * xs, 0.9)], -1)
    left = np.stack([xs, np.minimum(0.6 * xs, 0.9)], -1)
    plans = np.stack([right, left])
    # a person 4 m ahead walking head-on: keeping right lets them by on the robot's left (free)
    c = side_cost(plans, np.array([[4.0, 0.0]]), np.array([[-1.0, 0.0]]))
    assert c[0] == 0 and c[1] == 1
    # the same person crossing (90°), or standing, is no one's "oncoming": no side is asked for
    assert np.all(side_cost(plans, np.array([[4.0, 2.0]]), np.array([[0.0, -1.0]])) == 0)
    assert np.all(side_cost(plans, np.array([[4.0, 0.0]]), np.array([[0.0, 0.0]])) == 0)
    assert np.all(side_cost(plans, np.zeros((0, 2)), np.zeros((0, 2))) == 0)
