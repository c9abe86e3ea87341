"""The LLU buffer's coverage of the held-out doorway: head-on views, selection, held-out seeds."""

import numpy as np
import pytest

from splatsearch.social.convoi.scenario_names import LLU_ADAPT_SEEDS, LLU_TEST_SEEDS
from splatsearch.social.olivia import train as ot
from splatsearch.social.olivia.llu import LLUBuffer
from splatsearch.social.olivia.planner import oncoming_count
from splatsearch.social.olivia.render import IMG_H, IMG_W


def test_oncoming_count_on_hand_made_people():
    pose = np.array([0.0, 0.0, 0.0])  # facing +x
    people = np.array([[3.0, 0.1], [3.0, 0.0], [3.0, 2.5], [-2.0, 0.0], [2.0, 0.0]])
    vel = np.array([[-1.0, 0.0],   # ahead, walking at the robot: head-on
                    [1.0, 0.0],    # ahead, walking away
                    [0.0, -1.0],   # crossing far to the left
                    [1.0, 0.0],    # behind, walking toward it
                    [-0.1, 0.0]])  # ahead, head-on but nearly standing
    assert oncoming_count(pose, people, vel) == 1
    assert oncoming_count(pose, people[1:], vel[1:]) == 0
    # the same head-on person seen from a robot turned toward +y is not ahead any more
    assert oncoming_count(np.array([0.0, 0.0, np.pi / 2]), people[:1], vel[:1]) == 0
    assert oncoming_count(pose, np.zeros((0, 2)), np.zeros((0, 2))) == 0


def test_select_views_keeps_the_share_of_oncoming_views_spread():
    onc = np.zeros(200, int)
    onc[[20, 21, 22, 23, 150, 151]] = 1
    idx = ot.select_views(onc, 20, 0.5)
    assert len(idx) == 20 == len(set(idx)) and idx == sorted(idx)
    kept_on = [i for i in idx if onc[i]]
    assert len(kept_on) == 6  # fewer than half are oncoming: all of them
    others = [i for i in idx if not onc[i]]
    assert others[0] == 0 and others[-1] == 199  # the rest spread over the whole pool
    # a share caps them; too few others fill up with oncoming views
    onc2 = np.ones(30, int)
    onc2[:3] = 0
    idx2 = ot.select_views(onc2, 10, 0.2)
    assert sum(onc2[i] for i in idx2) == 7 and {0, 1, 2} <= set(idx2)
    with pytest.raises(ValueError):
        ot.select_views(onc2, 31, 0.5)


def test_fill_buffer_drives_every_seed_and_keeps_head_on_views(monkeypatch):
    driven, made = [], []

    def fake_episode(scn, planner, *, buffer, buffer_every, **kw):
        driven.append(scn.seed)
        for t in range(30):
            head_on = int(scn.seed == 505 and 10 <= t < 14)

            def scene(seed=scn.seed, t=t):
                made.append((seed, t))
                return ("scene", seed, t)

            buffer.add(np.full((IMG_H, IMG_W, 3), t / 30, np.float32), scene if buffer.lazy else scene(), None,
                       head_on, scn.seed)

    monkeypatch.setattr(ot, "run_olivia_episode", fake_episode)
    seeds = (500, 501, 502, 503, 504, 505)
    buf, used = ot.fill_buffer(None, "doorway", seeds, 20, oncoming_share=0.5)
    assert used == list(seeds) == driven
    assert buf.full and len(buf.images) == 20 and not buf.lazy
    assert sum(buf.oncoming) == 4 and {505} <= set(buf.episodes) and {500, 503} <= set(buf.episodes)
    # the captioner's (expensive) scene is made only for the views kept
    assert len(made) == 20 and buf.scenes[0][0] == "scene"
    # the first-views buffer of the old default never reaches seed 505
    driven.clear()
    made.clear()
    first, used_first = ot.fill_buffer(None, "doorway", seeds, 20)
    assert used_first == [500] and sum(first.oncoming) == 0
    with pytest.raises(ValueError):
        ot.fill_buffer(None, "doorway", seeds, 20, oncoming_share=1.5)


def test_lazy_buffer_select_makes_scenes():
    b = LLUBuffer(5, lazy=True)
    for i in range(5):
        b.add(np.zeros((2, 2, 3)), lambda i=i: i * 10, None, i % 2, 7)
    s = b.select([1, 3])
    assert s.scenes == [10, 30] and s.oncoming == [1, 1] and s.episodes == [7, 7] and s.full


def test_adaptation_and_test_seeds_are_held_apart():
    assert not set(LLU_ADAPT_SEEDS) & set(LLU_TEST_SEEDS)
    assert min(LLU_TEST_SEEDS) >= 1000 and max(LLU_ADAPT_SEEDS) < 1000
    with pytest.raises(ValueError, match="also test seeds"):
        ot.table_two(None, "doorway", (500, 1003), (1003, 1004))
