"""Simulator throughput (pytest-benchmark).

Run:  pytest benchmarks/test_sim_bench.py --benchmark-enable

Render frames per second at 320x240 (the target is >= 25 on the 2-core CPU) and 640x480, one
agent step (move + render), house generation, and the ground-truth navigable grid.
"""

import numpy as np
import pytest

from splatsearch import sim


@pytest.fixture(scope="module")
def env():
    e = sim.HouseEnv(sim.make_house(0))
    e.reset([*e.nav.cell_to_world(np.argwhere(e.nav.navigable)[2000]), 0.5])
    return e


@pytest.mark.parametrize("size", [(320, 240), (640, 480)])
def test_render(benchmark, env, size):
    w, h = size
    K = sim.intrinsics(w, h)
    vm = env.viewmat()
    env.renderer.render(vm, K, w, h)  # compile + allocate
    f = benchmark.pedantic(lambda: env.renderer.render(vm, K, w, h), rounds=10, iterations=1, warmup_rounds=1)
    assert f.rgb.shape == (h, w, 3)
    stats = getattr(benchmark, "stats", None)
    if stats is not None and getattr(stats, "stats", None) is not None:
        benchmark.extra_info["fps"] = 1.0 / stats.stats.mean


def test_agent_step(benchmark, env):
    actions = iter(["move_forward", "turn_left"] * 1000)
    obs = benchmark.pedantic(lambda: env.step(next(actions)), rounds=20, iterations=1)
    assert obs.frame.depth.shape == (240, 320)


def test_make_house(benchmark):
    h = benchmark.pedantic(lambda: sim.make_house(3), rounds=3, iterations=1)
    assert len(h.objects) > 0


def test_build_navgrid(benchmark):
    h = sim.make_house(3)
    sim.build_navgrid(h)
    g = benchmark.pedantic(lambda: sim.build_navgrid(h), rounds=3, iterations=1)
    assert g.navigable.any()
