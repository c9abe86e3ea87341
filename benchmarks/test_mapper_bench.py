"""Mapping speed (pytest-benchmark): seconds per frame at 320x240 with 15 iterations per frame.

Run:  pytest benchmarks/test_mapper_bench.py --benchmark-enable

The mapper first warms up on 12 frames of a simulator trajectory (so that the capacity and the
compiled step are those of a real run), then each benchmark round maps the next frame. Quality
(PSNR, SSIM, depth L1 on training and held-out views) is measured by
``splatsearch map --seed 0 --frames 100``.
"""

import pytest

from splatsearch.datasets import sim_trajectory
from splatsearch.mapper import Mapper, MapperConfig


@pytest.fixture(scope="module")
def warm():
    frames, K, W, H, _ = sim_trajectory(0, 40)
    m = Mapper(K, W, H, MapperConfig(iters=15, initial_capacity=1 << 16))
    for f in frames[:12]:
        m.update(f.rgb, f.depth, f.viewmat)
    return m, iter(frames[12:])


def test_map_frame_320x240_15_iters(benchmark, warm):
    m, frames = warm

    def one():
        f = next(frames)
        return m.update(f.rgb, f.depth, f.viewmat)

    st = benchmark.pedantic(one, rounds=10, iterations=1)
    benchmark.extra_info["gaussians"] = st["n_gaussians"]
    assert st["n_gaussians"] > 0
