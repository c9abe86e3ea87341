"""Rasterizer throughput (pytest-benchmark).

Run:  pytest benchmarks/test_rasterizer_bench.py --benchmark-enable
(with the project's default ``--benchmark-disable`` each case runs once, as a smoke test).

Cases: (a) the profile scene, 111,785 Gaussians on the surfaces of a procedural room at 648x420
RGB+D; (b) 10k random Gaussians at 320x240. Forward and forward + backward, after a warm-up,
with ``block_until_ready``. ``extra_info`` records the exact Gaussian-pixel evaluation count, the
evaluations per second and the fraction of the 2-core CPU's ~5 G/s forward ceiling.
"""

import jax
import pytest

from splatsearch import bench

SCENES = {
    "profile": lambda: bench.profile_scene(),
    "random10k": lambda: bench.random_scene(),
}


@pytest.fixture(scope="module", params=list(SCENES))
def setup(request):
    scene = SCENES[request.param]()
    fwd, fwd_bwd, params = bench.make_render_fns(scene)
    for _ in range(2):  # compile + warm the scratch buffers
        jax.block_until_ready(fwd(*params))
        jax.block_until_ready(fwd_bwd(*params))
    evals = bench.count_gaussian_pixel_evaluations(scene)
    return request.param, scene, fwd, fwd_bwd, params, evals


def _record(benchmark, evals, scene):
    benchmark.extra_info["gaussians"] = int(scene.means.shape[0])
    benchmark.extra_info["resolution"] = f"{scene.width}x{scene.height}"
    benchmark.extra_info["gaussian_pixel_evals"] = int(evals)
    stats = getattr(benchmark, "stats", None)
    if stats is not None and getattr(stats, "stats", None) is not None:
        mean = stats.stats.mean
        benchmark.extra_info["evals_per_s"] = evals / mean
        benchmark.extra_info["fraction_of_cpu_peak"] = evals / mean / bench.CPU_PEAK_EVALS_PER_S


def test_forward(benchmark, setup):
    name, scene, fwd, _, params, evals = setup
    out = benchmark.pedantic(lambda: jax.block_until_ready(fwd(*params)), rounds=5, iterations=1,
                             warmup_rounds=1)
    assert out[0].shape == (scene.height, scene.width, 3)
    _record(benchmark, evals, scene)


def test_forward_backward(benchmark, setup):
    name, scene, _, fwd_bwd, params, evals = setup
    val, grads = benchmark.pedantic(lambda: jax.block_until_ready(fwd_bwd(*params)), rounds=5, iterations=1,
                                    warmup_rounds=1)
    assert grads[0].shape == scene.means.shape
    _record(benchmark, evals, scene)
