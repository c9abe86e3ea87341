"""Rasterizer throughput (pytest-benchmark) on the four benchmark scenes of :mod:`splatsearch.bench`.

Run:  pytest benchmarks/test_rasterizer_bench.py --benchmark-enable
(with the project's default ``--benchmark-disable`` each case runs once, as a smoke test).

Scenes: (a) profile, 111,785 Gaussians on the surfaces of a procedural room at 648x420; (b) heavy,
the same room with scales U[5e-4, 0.1] m; (c) house, the mapper's map of simulator house 0
(24,562 Gaussians) from the middle pose of its walk at 320x240 and 640x480; (d) random10k at
320x240. RGB+D, forward and forward + backward, after a warm-up, with ``block_until_ready``.
``extra_info`` records the tile intersections, the exact Gaussian-pixel evaluation count of the
per-pixel forward loop, the evaluations per second and the fraction of the 2-core CPU's ~5 G/s.
Note ``uptime`` with every run: the machine is shared.
"""

import os

import jax
import pytest

from splatsearch import bench

CASES = [(name, i) for name, n in (("profile", 1), ("heavy", 1), ("house", 2), ("random10k", 1)) for i in range(n)]


@pytest.fixture(scope="module", params=CASES, ids=[f"{n}{i if n == 'house' else ''}" for n, i in CASES])
def setup(request):
    name, i = request.param
    label, scene = bench.scene_makers()[name]()[i]
    fwd, fwd_bwd, params = bench.make_render_fns(scene)
    for _ in range(2):  # compile + warm the scratch buffers
        jax.block_until_ready(fwd(*params))
        jax.block_until_ready(fwd_bwd(*params))
    from splatsearch.rasterization import rasterize

    n_isect = int(rasterize(*params, scene.width, scene.height).meta["n_isect"])
    evals = bench.count_gaussian_pixel_evaluations(scene)
    return label, scene, fwd, fwd_bwd, params, evals, n_isect


def _record(benchmark, label, scene, evals, n_isect):
    benchmark.extra_info["scene"] = label
    benchmark.extra_info["gaussians"] = int(scene.means.shape[0])
    benchmark.extra_info["resolution"] = f"{scene.width}x{scene.height}"
    benchmark.extra_info["tile_intersections"] = n_isect
    benchmark.extra_info["gaussian_pixel_evals"] = int(evals)
    benchmark.extra_info["load_average"] = os.getloadavg()[0]
    stats = getattr(benchmark, "stats", None)
    if stats is not None and getattr(stats, "stats", None) is not None:
        median = stats.stats.median
        benchmark.extra_info["evals_per_s"] = evals / median
        benchmark.extra_info["fraction_of_cpu_peak"] = evals / median / bench.CPU_PEAK_EVALS_PER_S


def test_forward(benchmark, setup):
    label, scene, fwd, _, params, evals, n_isect = setup
    out = benchmark.pedantic(lambda: jax.block_until_ready(fwd(*params)), rounds=5, iterations=1,
                             warmup_rounds=1)
    assert out[0].shape == (scene.height, scene.width, 3)
    _record(benchmark, label, scene, evals, n_isect)


def test_forward_backward(benchmark, setup):
    label, scene, _, fwd_bwd, params, evals, n_isect = setup
    val, grads = benchmark.pedantic(lambda: jax.block_until_ready(fwd_bwd(*params)), rounds=5, iterations=1,
                                    warmup_rounds=1)
    assert grads[0].shape == scene.means.shape
    _record(benchmark, label, scene, evals, n_isect)
