"""Social-navigation timings (pytest-benchmark).

Run:  python -m pytest benchmarks/test_social_bench.py --benchmark-enable

The target is >= 200 DWA plans per second on the CPU at 400 samples (20 x 20) x 30 steps, with
12 people, a reference path and the default critics; ``extra_info["plans_per_s"]`` holds the
rate. Also timed: other sample counts, a pedestrian-simulator step, one closed-loop control step
(perceive + plan + move + simulate), a CoNVOI update and a Fréchet distance. No timing is
asserted here or in the unit tests.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from splatsearch.social.convoi import metrics
from splatsearch.social.convoi import pedsim
from splatsearch.social.convoi.pipeline import CoNVOI
from splatsearch.social.convoi.dwa import DWAConfig, make_inputs, plan, reference_critic
from splatsearch.social.convoi.runner import Carry, control_step, make_world, planner_config
from splatsearch.social.convoi.scenarios import make_scenario
from splatsearch.social.convoi.vlm import RuleBasedVLM


def _rate(benchmark, key="per_s"):
    stats = getattr(benchmark, "stats", None)
    if stats is not None and getattr(stats, "stats", None) is not None:
        benchmark.extra_info["ms"] = round(1e3 * stats.stats.median, 3)
        benchmark.extra_info[key] = round(1.0 / stats.stats.median, 1)


@pytest.fixture(scope="module")
def scene():
    scn = make_scenario("static_groups", 0)
    return scn, make_world(scn, "dwa")


@pytest.mark.parametrize("n_v,n_w", [(20, 20), (10, 10), (40, 40)])
def test_dwa_plan(benchmark, scene, n_v, n_w):
    _, world = scene
    cfg = DWAConfig(n_v=n_v, n_w=n_w, n_steps=30).with_critic(reference_critic())
    rng = np.random.default_rng(0)
    inp = make_inputs([1.0, 0.0, 0.1], [0.4, 0.0], [4.0, 0.5], world.field, cfg,
                      people=rng.uniform(0, 6, (12, 2)), people_vel=rng.normal(0, 0.5, (12, 2)),
                      ref=[[2.0, -0.5], [3.0, -1.0], [4.0, -1.0]])
    jax.block_until_ready(plan(inp, cfg))  # compile outside the timing

    def run():
        return jax.block_until_ready(plan(inp, cfg).cmd)

    out = benchmark(run)
    assert np.all(np.isfinite(np.asarray(out)))
    benchmark.extra_info["samples"] = n_v * n_w
    _rate(benchmark, "plans_per_s")


def test_pedestrian_step(benchmark, scene):
    scn, world = scene
    cfg = pedsim.SocialForceConfig()
    key = jax.random.PRNGKey(0)
    args = (scn.peds, world.capsules, world.capsules_valid, jnp.zeros(2, jnp.float32), jnp.zeros(2, jnp.float32), key)
    jax.block_until_ready(pedsim.step(*args, cfg))
    benchmark(lambda: jax.block_until_ready(pedsim.step(*args, cfg)[0].pos))
    _rate(benchmark, "steps_per_s")


@pytest.mark.parametrize("kind", ["dwa", "expert"])
def test_control_step(benchmark, scene, kind):
    scn, _ = scene
    world = make_world(scn, kind)
    cfg = planner_config(kind)
    sf = pedsim.SocialForceConfig()
    carry = Carry(jnp.asarray(scn.start, jnp.float32), jnp.zeros(2, jnp.float32), scn.peds, jnp.asarray(0, jnp.int32))
    ref, rv = jnp.zeros((16, 2), jnp.float32), jnp.zeros(16, bool)
    key = jax.random.PRNGKey(0)
    jax.block_until_ready(control_step(carry, world, ref, rv, jnp.asarray(False), key, kind, cfg, sf))
    benchmark(lambda: jax.block_until_ready(
        control_step(carry, world, ref, rv, jnp.asarray(False), key, kind, cfg, sf)[0].pose))
    _rate(benchmark, "steps_per_s")


def test_convoi_update(benchmark, scene):
    scn, _ = scene
    world = make_world(scn, "convoi")
    cv = CoNVOI(RuleBasedVLM())
    cv.update(0.0, scn.start, scn.peds, world)
    t = iter(np.arange(1, 10 ** 6) * 0.1)
    # the robot stays put, so most calls classify the context and keep the path; some re-query
    benchmark(lambda: cv.update(next(t), scn.start, scn.peds, world))
    _rate(benchmark, "updates_per_s")


def test_frechet(benchmark):
    rng = np.random.default_rng(0)
    a = np.cumsum(rng.normal(size=(300, 2)), 0)
    b = np.cumsum(rng.normal(size=(250, 2)), 0)
    metrics.frechet(a, b)
    benchmark(lambda: metrics.frechet(a, b))
    _rate(benchmark, "per_s")


def test_human_walker_step(benchmark, scene):
    """One step of the human-like reference walker (plan over the route against the forked
    people's 4-s future, move, step the people)."""
    from splatsearch.social.convoi.human import HumanWalkerConfig, WalkerCarry, make_walker_world, walker_step

    scn, _ = scene
    world = make_walker_world(scn)
    cfg = HumanWalkerConfig()
    sf = pedsim.SocialForceConfig()
    carry = WalkerCarry(jnp.asarray(scn.start, jnp.float32), jnp.zeros(2, jnp.float32), scn.peds,
                        jnp.asarray(0, jnp.int32), jnp.asarray(0.0, jnp.float32))
    key = jax.random.PRNGKey(0)
    jax.block_until_ready(walker_step(carry, world, key, cfg, sf)[0].pose)
    benchmark(lambda: jax.block_until_ready(walker_step(carry, world, key, cfg, sf)[0].pose))
    _rate(benchmark, "steps_per_s")
