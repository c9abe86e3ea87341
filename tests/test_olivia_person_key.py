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
