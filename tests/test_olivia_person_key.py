"""D_T's person key (person_key.py): its construction, and that view entries with equal image keys
are told apart by the perceived person state."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from splatsearch.social.olivia.captions import ACTIONS
from splatsearch.social.olivia.llu import LLUBuffer, TextDB, add_view_entries
from splatsearch.social.olivia.person_key import PERSON_SCALE, person_distance2, person_state
from splatsearch.social.olivia.planner import OliviaConfig, person_penalty, retrieve

RIGHT = "a person walks toward you through the door you should keep to the right"
STRAIGHT = "a person walks across the hall you should continue moving straight ahead at a steady pace"


def test_person_state_is_the_nearest_person_ahead_in_the_robot_frame():
    pose = np.array([0.0, 0.0, 0.0])
    s = person_state(pose, np.array([[5.0, 1.0], [-1.0, 0.0], [8.0, 0.0]]), np.array([[-1.0, 0.0], [0, 0], [0, 0]]))
    r = np.hypot(5, 1)
    np.testing.assert_allclose(s, [r, np.arctan2(1, 5), 5 / r, 1.0], rtol=1e-5)  # the one behind is ignored
    # turning the robot by +90° puts a person straight ahead on the new x axis, at lateral 0
    s2 = person_state(np.array([1.0, 1.0, np.pi / 2]), np.array([[1.0, 4.0]]), np.array([[0.0, -1.2]]))
    np.testing.assert_allclose(s2, [3.0, 0.0, 1.2, 0.0], atol=1e-5)
    # someone walking away closes at a negative speed; on the robot's right the bearing is negative
    s3 = person_state(pose, np.array([[3.0, -1.0]]), np.array([[1.0, 0.0]]))
    assert s3[1] < 0 and s3[2] < 0 and s3[3] == pytest.approx(-1.0)
    assert np.all(np.isnan(person_state(pose, np.array([[-2.0, 0.0]]), np.zeros((1, 2)))))
    assert np.all(np.isnan(person_state(pose, np.zeros((0, 2)), np.zeros((0, 2)))))


def test_person_distance_is_scaled_and_infinite_without_a_person():
    s = np.array([5.0, 0.1, 1.0, 0.5], np.float32)
    keys = np.stack([s, s + PERSON_SCALE * np.array([1, 0, 0, 0]), np.full(4, np.nan)]).astype(np.float32)
    np.testing.assert_allclose(person_distance2(s, keys), [0.0, 1.0, np.inf])


def test_view_entries_carry_person_keys_and_buffer_keeps_them():
    db = TextDB(np.eye(3, 4, dtype=np.float32), ["a", "b", "c"], np.array([0, 1, 2], np.int32))
    ps = np.array([[5, 0, 1, 0], [np.nan] * 4], np.float32)
    dbv = add_view_entries(db, np.ones((2, 4)), np.ones((2, 4)), [RIGHT, STRAIGHT], ps)
    assert dbv.persons.shape == (5, 4) and np.all(np.isnan(dbv.persons[:3]))
    np.testing.assert_allclose(dbv.persons[3], ps[0])
    assert add_view_entries(db, np.ones((2, 4)), np.ones((2, 4)), [RIGHT, STRAIGHT]).persons is None
    buf = LLUBuffer(2)
    buf.add(np.zeros((2, 2, 3)), person=ps[0])
    buf.add(np.zeros((2, 2, 3)))
    sel = buf.select([1, 0])
    assert np.all(np.isnan(sel.persons[0])) and np.allclose(sel.persons[1], ps[0])


def _equal_image_db() -> TextDB:
    """Two offline captions and two view entries with the SAME image key, one captioned for a
    head-on person 6 m ahead closing at 1 m/s (keep right), one for a person crossing 6 m ahead
    (straight)."""
    emb = np.eye(4, 8, dtype=np.float32)
    db = TextDB(emb[:2], ["x", "y"], np.array([0, 2], np.int32))
    view = np.zeros((2, 8), np.float32)
    view[:, 5] = 1.0
    persons = np.array([[6.0, 0.05, 1.0, 0.3], [6.0, 0.5, 0.0, 2.9]], np.float32)
    return add_view_entries(db, view, emb[2:4], [RIGHT, STRAIGHT], persons)


def test_equal_images_are_retrieved_by_person_state():
    db = _equal_image_db()
    cfg = OliviaConfig(person_key=True)
    e = np.zeros(8, np.float32)
    e[5] = 1.0  # the query view looks exactly like both view entries
    keys, acts = jnp.asarray(db.key_matrix), jnp.asarray(db.actions)
    got = {}
    for name, s in {"head_on": [5.6, 0.0, 1.1, 0.2], "crossing": [6.2, 0.45, 0.1, 2.7]}.items():
        pen, ok, _ = person_penalty(db, np.asarray(s, np.float32), cfg)
        j, _ = retrieve(keys, acts, jnp.asarray(e), 1, 0.05, None, jnp.asarray(pen))
        got[name] = int(j)
        assert ok[int(j)]
    assert ACTIONS[db.actions[got["head_on"]]] == "keep_right"
    assert ACTIONS[db.actions[got["crossing"]]] == "straight"
    # a person state far from both keys still ranks them but fails the person gate
    pen, ok, _ = person_penalty(db, np.array([1.0, -1.0, -1.0, -1.0], np.float32), cfg)
    assert not ok[2] and not ok[3] and ok[0] and ok[1]
    # off (the thesis' image-only key) or without a person state: no penalty, every entry ok
    for c, s in ((dataclasses.replace(cfg, person_key=False), np.zeros(4, np.float32)), (cfg, None)):
        pen, ok, gate = person_penalty(db, s, c)
        assert not np.any(pen) and np.all(ok)
        np.testing.assert_allclose(gate, [c.text_gate] * 2 + [c.view_gate] * 2)


def test_nobody_ahead_matches_a_view_entry_with_nobody_ahead_only():
    db = _equal_image_db()
    db = add_view_entries(db, np.eye(1, 8, 5), np.eye(1, 8, 6), [STRAIGHT], np.full((1, 4), np.nan))
    pen, ok, _ = person_penalty(db, np.full(4, np.nan, np.float32), OliviaConfig(person_key=True))
    assert ok[4] and pen[4] == 0 and not ok[2] and not ok[3]


def test_person_view_gate_lets_a_matched_view_entry_rank_first_and_opens_its_gate():
    db = _equal_image_db()
    cfg = OliviaConfig(person_key=True, person_view_gate=0.5)
    s = np.array([5.6, 0.0, 1.1, 0.2], np.float32)
    pen, ok, gate = person_penalty(db, s, cfg)
    assert gate[2] == pytest.approx(0.5) and gate[3] == pytest.approx(cfg.view_gate) and gate[0] == pytest.approx(cfg.text_gate)
    assert pen[2] < -0.9 and ok[2] and not ok[3]
    # nobody seen: no entry is person-matched, the gates are the usual ones
    _, _, gate = person_penalty(db, np.full(4, np.nan, np.float32), cfg)
    assert gate[2] == pytest.approx(cfg.view_gate)


@pytest.mark.slow  # XLA compilation of the full planner (default networks) on 2 cores
def test_planner_with_equal_view_images_follows_the_person_state():
    """The whole plan cycle: two view entries keyed by the very same E_I (this view's), captioned
    keep right (head-on person) and straight (crossing person); the perceived person decides which
    caption the planner retrieves and uses, and with the key off the first one is taken."""
    import jax

    from splatsearch.social.olivia import sc_clip, tpn, tsm
    from splatsearch.social.olivia import train as ot
    from splatsearch.social.olivia.features import GOAL_DIM
    from splatsearch.social.olivia.lidar import N_POINTS
    from splatsearch.social.olivia.llu import build_text_db
    from splatsearch.social.olivia.planner import OliviaNav
    from splatsearch.social.olivia.render import IMG_H, IMG_W

    cfg = OliviaConfig(person_key=True)
    k = jax.random.split(jax.random.PRNGKey(0), 3)
    params = {"clip": sc_clip.init_sc_clip(k[0], cfg.clip), "tpn": tpn.init_tpn(k[1], cfg.tpn),
              "tsm": tsm.init_tsm(k[2], cfg.tsm)}
    db = build_text_db(params["clip"], ["the space is open you should continue straight"], cfg.clip)
    rng = np.random.default_rng(0)
    obs = (rng.integers(0, 255, (IMG_H, IMG_W, 3)).astype(np.uint8), rng.normal(size=(N_POINTS, 4)).astype(np.float32),
           np.ones(N_POINTS, bool), rng.normal(size=GOAL_DIM).astype(np.float32))
    e_i = ot.encode_all_images(params["clip"], obs[0][None], cfg.clip)
    caps = [RIGHT, STRAIGHT]
    persons = np.array([[6.0, 0.05, 1.0, 0.3], [6.0, 0.5, 0.0, 2.9]], np.float32)
    dbv = add_view_entries(db, np.repeat(e_i, 2, 0), ot.encode_all_texts(params["clip"], caps, cfg.clip), caps, persons)
    planner = OliviaNav(params, dbv, cfg)
    head_on = planner.plan(*obs, person=np.array([5.6, 0.0, 1.1, 0.2], np.float32))
    crossing = planner.plan(*obs, person=np.array([6.2, 0.45, 0.1, 2.7], np.float32))
    assert head_on.caption == RIGHT and head_on.text_used
    assert crossing.caption == STRAIGHT and crossing.text_used
    # a person far from both keys: the entry is still ranked but E_T is not used
    assert not planner.plan(*obs, person=np.array([1.0, -1.0, -1.0, -1.0], np.float32)).text_used
    off = OliviaNav(params, dbv, dataclasses.replace(cfg, person_key=False)).plan(*obs, person=persons[1])
    assert off.caption == RIGHT  # image-only key: the two entries tie and the first is taken
