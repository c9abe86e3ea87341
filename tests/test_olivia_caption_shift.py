"""The LLU captioner forks the reference walker with the lateral shift the reference holds (stop 45).

A walker forked with no side chosen can undo a sidestep the reference has just begun (its change
cost flips it back), so the template captioner used to say "keep left" where the reference keeps
right on the head-on doorway. These tests pin the pieces of the fix: the walker's episode records
its carried shift, a fork with that shift is the episode itself, and the buffer's captioner gets it.
"""

import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from splatsearch.social.convoi import pedsim
from splatsearch.social.convoi.human import HumanWalkerConfig, WalkerCarry, make_walker_world, run_walker, walker_rollout, walker_step
from splatsearch.social.convoi.scenarios import ROBOT_RADIUS, _box, _scn
from splatsearch.social.olivia import train as ot
from splatsearch.social.olivia.render import IMG_H, IMG_W

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))


def head_on_scene():
    """An open room; one person walks along the robot's line straight at it (the walker steps aside)."""
    caps = _box(-1.5, -4.0, 12.5, 4.0)
    return _scn("hallway", 0, caps, [0.0, 0.0, 0.0], [10.0, 0.0], [[6.0, 0.0]], [[[-1.0, 0.0]]], [0.9], max_steps=60)


def test_walker_episode_records_the_shift_and_a_fork_with_it_is_the_episode():
    scn = head_on_scene()
    n = 40
    res = run_walker(scn, max_steps=n)
    assert res.shifts is not None and res.shifts.shape == (len(res.robot),) and res.shifts[0] == 0.0
    assert np.min(res.shifts) < -0.1  # it stepped aside to the right of the oncoming person
    # the people at step t, as the episode stepped them (the walker's own loop)
    cfg = HumanWalkerConfig()
    sf = pedsim.SocialForceConfig(dt=scn.dt, robot_radius=ROBOT_RADIUS)
    world, key = make_walker_world(scn, cfg), jax.random.PRNGKey(scn.seed)
    t = int(np.argmax(np.abs(res.shifts) > 0.1)) + 2  # just after it chose its side
    carry = WalkerCarry(jnp.asarray(scn.start, jnp.float32), jnp.zeros(2, jnp.float32), scn.peds,
                        jnp.asarray(0, jnp.int32), jnp.asarray(0.0, jnp.float32))
    for _ in range(t):
        carry, *_ = walker_step(carry, world, key, cfg, sf)
    assert float(carry.offset) == pytest.approx(float(res.shifts[t]))
    k = min(10, n - t)
    fork = walker_rollout(scn, res.robot[t], res.cmds[t - 1], carry.peds, t, k, offset=float(res.shifts[t]))
    np.testing.assert_allclose(fork[: k + 1, :2], res.robot[t: t + k + 1, :2], atol=1e-5)


def test_reference_shift_of_reads_the_episode_once_and_holds_its_end(monkeypatch):
    calls = []

    class Ref:
        shifts = np.array([0.0, -0.3, -0.6, -0.9], np.float32)

    def fake_baseline(scn, kind, cache=None):
        calls.append((scn, kind))
        return Ref()

    monkeypatch.setattr(ot, "run_baseline", fake_baseline)
    f = ot.reference_shift_of("scn")
    assert f(0) == 0.0 and f(2) == pytest.approx(-0.6) and f(50) == pytest.approx(-0.9)
    assert calls == [("scn", "human")]


def test_fill_buffer_hands_each_episode_its_reference_shift(monkeypatch):
    got = {}

    class Ref:
        def __init__(self, seed):
            self.shifts = np.full(5, -0.01 * (seed - 500), np.float32)

    monkeypatch.setattr(ot, "run_baseline", lambda scn, kind, cache=None: Ref(scn.seed))

    def fake_episode(scn, planner, *, buffer, buffer_every, reference_shift=None):
        got[scn.seed] = reference_shift
        for _ in range(30):
            buffer.add(np.zeros((IMG_H, IMG_W, 3), np.float32))

    monkeypatch.setattr(ot, "run_olivia_episode", fake_episode)
    ot.fill_buffer(None, "doorway", (500, 502), 50)
    assert got[500](3) == 0.0 and got[502](3) == pytest.approx(-0.02)
    ot.fill_buffer(None, "doorway", (500,), 20, carry_shift=False)
    assert got[500] is None


@pytest.mark.slow  # the reference walker's doorway episode and two 4-s rollouts (~1-2 min alone)
def test_captioner_keeps_the_head_on_sidestep_the_reference_chose(tmp_path, monkeypatch):
    """Dev doorway seed 309 at 2.0 s: the reference has begun its sidestep right (shift -0.6 m) and
    keeps right; the captioner forked with no shift said keep left (stop 44), with the reference's
    shift it says what the reference does. Checked on the omniscient walker: the perceiving one
    (the default since stop 46) does not see the person before 2.1 s there and passes them on the
    left, so 309 holds no sidestep to keep."""
    import olivia_caption_vs_reference as cr

    from splatsearch.social.convoi import runner

    monkeypatch.setattr(runner, "REFERENCE", "human_omniscient")

    from splatsearch.social.olivia.baseline_cache import BaselineCache

    cache = BaselineCache(str(tmp_path / "cache"))
    carried = cr.along_reference("doorway", 309, [20], cache, carry_shift=True)[0]
    fresh = cr.along_reference("doorway", 309, [20], cache, carry_shift=False)[0]
    assert carried["shift"] < -0.3 and carried["reference"] == "keep_right"
    assert carried["caption"] == "keep_right"
    assert fresh["caption"] == "keep_left"  # the defect the shift fixes
