"""Navigation layer timings (pytest-benchmark).

Run:  python -m pytest benchmarks/test_nav_bench.py --benchmark-enable

The target is an occupancy update of <= 20 ms per 320x240 depth frame on the default 1000 x 1000
grid (5 cm cells). Also timed: frontier extraction, one FMM solve from the robot, one planning
step toward a frontier, the value-map fusion (JAX), the default image encoder, and a whole
exploration decision, all on a house map built from ~160 views.
"""

import numpy as np
import pytest
from splatsearch.nav import (
    ColorTextureEncoder,
    ExplorationConfig,
    ExplorationPlanner,
    GridSpec,
    OccupancyGrid,
    ValueMap,
    attach_distances,
    extract_frontiers,
)

from splatsearch import sim


def _ms(benchmark):
    stats = getattr(benchmark, "stats", None)
    if stats is not None and getattr(stats, "stats", None) is not None:
        benchmark.extra_info["ms"] = round(1e3 * stats.stats.mean, 3)


@pytest.fixture(scope="module")
def house_env():
    env = sim.HouseEnv(sim.make_house(0))
    start = env.nav.cell_to_world(np.argwhere(env.nav.navigable)[2000])
    return env, start


def _frames(env, start, w, h, n=12):
    K = sim.intrinsics(w, h)
    out = []
    for i in range(n):
        vm = sim.camera_viewmat(start[0], start[1], i * np.pi / 6)
        out.append((env.renderer.render(vm, K, w, h).depth, vm, K))
    return out


@pytest.mark.parametrize("size", [(320, 240), (640, 480)])
def test_occupancy_update(benchmark, house_env, size):
    env, start = house_env
    frames = _frames(env, start, *size)
    occ = OccupancyGrid(GridSpec.centered(start))  # 1000 x 1000 cells of 5 cm
    assert occ.shape == (1000, 1000)
    it = iter(range(10 ** 9))

    def run():
        d, vm, K = frames[next(it) % len(frames)]
        return occ.update(d, vm, K)

    fp = benchmark.pedantic(run, rounds=48, iterations=1, warmup_rounds=2)
    assert fp.visible.any()
    _ms(benchmark)


@pytest.fixture(scope="module")
def explored(house_env):
    """Occupancy + value map of house 0 from 40 navigable spots x 4 headings."""
    env, start = house_env
    spec = GridSpec.centered(start)
    occ = OccupancyGrid(spec)
    vm = ValueMap(spec)
    rng = np.random.default_rng(0)
    cells = np.argwhere(env.nav.navigable)
    for rc in cells[rng.choice(len(cells), 40, replace=False)]:
        xy = env.nav.cell_to_world(rc)
        for k in range(4):
            v = sim.camera_viewmat(xy[0], xy[1], k * np.pi / 2 + rng.uniform(0, 1))
            fp = occ.update(env.renderer.render(v, env.K, 320, 240).depth, v, env.K)
            vm.update(float(rng.uniform(-1, 1)), fp)
    return spec, occ, vm, start


def test_frontier_extraction(benchmark, explored):
    spec, occ, _, _ = explored
    fs = benchmark.pedantic(lambda: extract_frontiers(occ.state, spec), rounds=20, iterations=1, warmup_rounds=1)
    benchmark.extra_info["frontiers"] = len(fs)
    _ms(benchmark)


def test_fmm_distance_from_robot(benchmark, explored):
    spec, occ, _, start = explored
    ep = ExplorationPlanner(spec, occupancy=occ)
    planner = ep.planner()
    D = benchmark.pedantic(lambda: planner.distance_from(start), rounds=20, iterations=1, warmup_rounds=1)
    fs = attach_distances(extract_frontiers(occ.state, spec), D, spec)
    benchmark.extra_info["reachable_cells"] = int(np.isfinite(D).sum())
    benchmark.extra_info["reachable_frontiers"] = len(fs)
    _ms(benchmark)


def test_fmm_plan_step(benchmark, explored):
    spec, occ, _, start = explored
    ep = ExplorationPlanner(spec, occupancy=occ)
    fs = ep.frontiers([*start, 0.0])
    assert fs
    goal = fs[-1].waypoint_xy

    def run():
        planner = ep.planner()  # a fresh map every step, as in the loop: no cached goal field
        return planner.plan([*start, 0.0], goal, 0.5)

    p = benchmark.pedantic(run, rounds=10, iterations=1, warmup_rounds=1)
    assert p.status in ("moving", "blocked")
    _ms(benchmark)


def test_value_map_fusion(benchmark, house_env):
    env, start = house_env
    spec = GridSpec.centered(start)
    occ = OccupancyGrid(spec)
    fps = [occ.update(d, v, K) for d, v, K in _frames(env, start, 320, 240)]
    vm = ValueMap(spec)
    for fp in fps:  # compile every window size once
        vm.update(0.1, fp)
    vm.value.block_until_ready()
    it = iter(range(10 ** 9))

    def run():
        vm.update(0.5, fps[next(it) % len(fps)])
        vm.value.block_until_ready()

    benchmark.pedantic(run, rounds=36, iterations=1, warmup_rounds=1)
    _ms(benchmark)


def test_encoder_embed(benchmark, house_env):
    env, start = house_env
    rgb = env.renderer.render(sim.camera_viewmat(*start, 0.0), env.K, 320, 240).rgb
    enc = ColorTextureEncoder()
    e = benchmark.pedantic(lambda: enc.embed(rgb), rounds=20, iterations=1, warmup_rounds=1)
    assert e.shape == (enc.dim,)
    _ms(benchmark)


def test_exploration_decision(benchmark, explored):
    spec, occ, vm, start = explored
    ep = ExplorationPlanner(spec, ExplorationConfig(alpha=1.0, delta=1.0, initial_turns=0), occupancy=occ,
                            value_map=vm)
    d = benchmark.pedantic(lambda: ep.act([*start, 0.0]), rounds=10, iterations=1, warmup_rounds=1)
    assert d.action in ("move_forward", "turn_left", "turn_right", "stop")
    _ms(benchmark)
