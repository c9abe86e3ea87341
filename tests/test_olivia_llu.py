"""One LLU update (eq 4) changes the TSM's choice on a hand-made case: the views' captions ask for
another action than D_T's offline captions, and after the update D_T retrieves the new caption
for those views, whose E_T moves the TSM to the plan performing that action."""

import jax
import jax.numpy as jnp
import numpy as np
import optax

from splatsearch.social.olivia import sc_clip, tsm
from splatsearch.social.olivia.captions import ACTIONS, action_from_text
from splatsearch.social.olivia.features import HORIZON, action_of
from splatsearch.social.olivia.llu import LLUConfig, build_text_db, llu_update
from splatsearch.social.olivia.render import IMG_H, IMG_W

TINY = sc_clip.SCCLIPConfig(width=32, depth=1, heads=2, mlp=64, text_width=32, text_depth=1, text_heads=2,
                            text_mlp=64, embed=16, pce_k=4, text_len=40)
SMALL_TSM = tsm.TSMConfig(embed=16, width=32, K=3)
OLD = "a doorway ahead with a person coming through it you should continue straight"
NEW = "a doorway ahead with a person coming through it you should slow down and yield"
OTHER = "an open room with nobody near you should keep to the left"


def _plans():
    t = np.linspace(0.1, 1.0, HORIZON)
    z = 0 * t
    straight = np.stack([2.4 * t, z, z], -1)
    left = np.stack([2.4 * t, 0.8 * t ** 2, 0.3 * t], -1)
    stop = np.stack([0.3 * t, z, z], -1)
    plans = np.stack([straight, left, stop]).astype(np.float32)
    assert [ACTIONS[action_of(p)] for p in plans] == ["straight", "keep_left", "yield"]
    return plans


def _images():
    rng = np.random.default_rng(0)
    door = np.full((IMG_H, IMG_W, 3), 60, np.uint8)
    door[:, IMG_W // 3: 2 * IMG_W // 3] = 200
    room = np.full((IMG_H, IMG_W, 3), 150, np.uint8)
    return [np.clip(im.astype(int) + rng.integers(0, 15, im.shape), 0, 255).astype(np.uint8) for im in (door, room)]


def _train_tsm(clip_p, plans):
    """The TSM trained on rows (caption -> the plan performing its action), as eq 7 does."""
    caps = [OLD, NEW, OTHER]
    db = build_text_db(clip_p, caps, TINY)
    e = jnp.asarray(db.embeddings)
    k = jnp.asarray([0, 2, 1])  # OLD -> straight, NEW -> yield, OTHER -> keep_left
    trajs = jnp.broadcast_to(jnp.asarray(plans), (3,) + plans.shape)
    p = tsm.init_tsm(jax.random.PRNGKey(0), SMALL_TSM)
    opt = optax.adam(3e-3)
    st = opt.init(p)
    model = tsm.TSM(SMALL_TSM)

    @jax.jit
    def step(p, st):
        lv, g = jax.value_and_grad(lambda p: tsm.tsm_loss(model.apply({"params": p}, e, trajs, jnp.ones(3, bool)),
                                                         k))(p)
        u, st = opt.update(g, st, p)
        return optax.apply_updates(p, u), st, lv

    for _ in range(200):
        p, st, lv = step(p, st)
    assert float(lv) < 0.05
    return p


def test_one_llu_update_moves_the_tsm_to_the_plan_of_the_new_caption():
    clip_p = sc_clip.init_sc_clip(jax.random.PRNGKey(3), TINY)
    plans = _plans()
    tsm_p = _train_tsm(clip_p, plans)
    door, room = _images()
    enc = jax.jit(lambda p, x: sc_clip.encode_images(p, x, TINY))

    def choose(clip_p, db):
        e_i = np.asarray(enc(clip_p, jnp.asarray(door[None])))[0]
        j, e_t = db.retrieve(e_i)
        logits = tsm.TSM(SMALL_TSM).apply({"params": tsm_p}, jnp.asarray(e_t[None]), jnp.asarray(plans[None]),
                                          jnp.ones(1, bool))
        return db.captions[j], int(np.argmax(np.asarray(logits)[0]))

    # before: D_T holds the offline captions only; the door view retrieves "continue straight"
    db0 = build_text_db(clip_p, [OLD, OTHER], TINY)
    cap0, k0 = choose(clip_p, db0)
    assert action_from_text(cap0) != ACTIONS.index("yield")
    # the buffer: door views captioned "yield" (the VLM's judgement), room views "keep left"
    imgs = np.stack([door, room] * 8)
    caps = [NEW, OTHER] * 8
    new_p, losses = llu_update(clip_p, imgs, caps, LLUConfig(size=16, steps=60, lr=1e-3, batch=16), TINY)
    assert losses[-1] < losses[0]
    db1 = build_text_db(new_p, [OLD, OTHER] + caps, TINY)
    assert len(db1.captions) == 3 and NEW in db1.captions  # D_T gained the new caption (duplicates merged)
    # the TSM is unchanged by the LLU (eq 4 fine-tunes the encoders); only E_T changed
    cap1, k1 = choose(new_p, db1)
    assert cap1 == NEW
    assert k1 != k0 and ACTIONS[action_of(plans[k1])] == "yield"
