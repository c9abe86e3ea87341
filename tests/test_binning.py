"""The CPU binning (a counting sort by tile in depth order, chunked over threads) builds exactly
the lists of the key radix sort that CUDA uses, whatever the thread count."""

import numpy as np
import pytest
import warp as wp

from splatsearch import bench
from splatsearch.kernels import pipeline as pl


def _projected(sc):
    n = sc.means.shape[0]
    arr = lambda x, dt: wp.array(x, dtype=dt, device="cpu")  # noqa: E731
    opac = arr(sc.opacities, wp.float32)
    out = (wp.empty(n, dtype=wp.vec2, device="cpu"), wp.empty(n, dtype=wp.vec3, device="cpu"),
           wp.empty(n, dtype=wp.float32, device="cpu"), wp.empty(n, dtype=wp.vec2i, device="cpu"))
    pl.project(arr(sc.means, wp.vec3), arr(sc.quats, wp.vec4), arr(sc.scales, wp.vec3), opac,
               arr(sc.viewmat[None], wp.mat44), arr(sc.K[None], wp.mat33), sc.width, sc.height, 0.01, 1e10, 0.3,
               *out, threads=1)
    means2d, conics, depths, radii = out
    return means2d, conics, opac, depths, radii


def _key_sort_lists(sc, means2d, conics, opac, depths, radii):
    ws = pl.Workspace("cpu")
    pl.bin_gaussians(ws, means2d, conics, opac, depths, radii, sc.width, sc.height, threads=1)  # depth order
    order = ws.get("order", 2 * means2d.shape[0], wp.int32)
    tx, ty = pl.grid_dims(sc.width, sc.height)
    ranges = ws.get2d("ranges", tx * ty, 2, wp.int32, zero=True)
    r, ids, k = pl._bin_by_key_sort(ws, order, means2d, conics, opac, radii, sc.width, sc.height, pl.TILE_SIZE,
                                    ranges, None, 1)
    return r.numpy().copy(), ids.numpy().copy(), k


@pytest.mark.parametrize("scene", ["heavy_crop", "random_small"])
def test_counting_binning_equals_key_sort(scene):
    if scene == "heavy_crop":  # 112k Gaussians (chunked), boxes past 31 tiles, 77 tiles
        sc = bench.heavy_scene(width=162, height=105)
    else:  # below the threading threshold: one chunk
        sc = bench.random_scene(n=2000, width=90, height=70)
    proj = _projected(sc)
    ref_ranges, ref_ids, ref_n = _key_sort_lists(sc, *proj)
    assert ref_n > 0
    for threads in (1, 2, 3):
        ws = pl.Workspace("cpu")  # owns the returned buffers: keep it alive
        ranges, ids, n = pl.bin_gaussians(ws, *proj, sc.width, sc.height, threads=threads)
        assert n == ref_n
        np.testing.assert_array_equal(ranges.numpy(), ref_ranges)
        np.testing.assert_array_equal(ids.numpy(), ref_ids)
    # every tile's list is in front-to-back order
    depths = proj[3].numpy()
    for t0, t1 in ref_ranges:
        assert np.all(np.diff(depths[ref_ids[t0:t1]]) >= 0)


def test_binning_with_nothing_visible():
    sc = bench.random_scene(n=50, width=40, height=30)
    means2d, conics, opac, depths, radii = _projected(sc)
    radii.zero_()  # every Gaussian culled
    ws = pl.Workspace("cpu")
    ranges, ids, n = pl.bin_gaussians(ws, means2d, conics, opac, depths, radii, 40, 30, threads=2)
    assert n == 0 and ids.shape[0] == 0
    assert not ranges.numpy().any()
