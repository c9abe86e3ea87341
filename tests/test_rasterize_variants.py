"""The two compositing kernels agree on dense, realistic and needle-thin scenes; run options are
arguments whose defaults the environment may set."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scenes import ON_CUDA

import splatsearch
from splatsearch import bench


def _heavy_crop():
    """Scene (b) of the benchmarks at a quarter of its resolution: heavy overlap, saturated pixels."""
    return bench.heavy_scene(width=162, height=105)


def _needles(n=400, seed=0):
    """Needle- and sheet-like Gaussians (axis ratios up to 1e4) around the camera's view axis."""
    rng = np.random.default_rng(seed)
    means = rng.normal(0, 0.6, (n, 3)) + [0, 0, 3.0]
    q = rng.normal(size=(n, 4))
    scales = np.exp(rng.uniform(np.log(1e-4), np.log(1.0), (n, 3)))
    f = lambda a: np.asarray(a, np.float32)  # noqa: E731
    return (f(means), f(q / np.linalg.norm(q, axis=1, keepdims=True)), f(scales), f(rng.uniform(0.05, 1, n)),
            f(rng.uniform(0, 1, (n, 3))), np.eye(4, dtype=np.float32), bench.intrinsics_from_hfov(97, 61, 70.0))


def _render(args, W, H, composite, threads=None):
    out = splatsearch.rasterize(*args, W, H, render_mode="RGB+D", composite=composite, threads=threads)
    return [np.asarray(x) for x in (out.image, out.depth, out.alpha)], int(out.meta["n_isect"])


def _grads(args, W, H, composite):
    rng = np.random.default_rng(1)
    wc = jnp.asarray(rng.uniform(-1, 1, (H, W, 3)), jnp.float32)

    def loss(m, q, s, o, c):
        out = splatsearch.rasterize(m, q, s, o, c, args[5], args[6], W, H, composite=composite)
        return jnp.sum(out.image * wc) + 0.1 * jnp.sum(out.depth) + jnp.sum(out.alpha)

    return [np.asarray(g) for g in jax.grad(loss, argnums=(0, 1, 2, 3, 4))(*[jnp.asarray(a) for a in args[:5]])]


@pytest.mark.parametrize("which", ["heavy_crop", "needles"])
def test_tile_and_pixel_kernels_agree(which):
    if which == "heavy_crop":
        sc = _heavy_crop()
        args, W, H = sc.args[:7], sc.width, sc.height
    else:
        args, W, H = _needles(), 97, 61
    (img_t, dep_t, alp_t), ni_t = _render(args, W, H, "tile")
    (img_p, dep_p, alp_p), ni_p = _render(args, W, H, "pixel")
    assert ni_t == ni_p > 0
    assert float(alp_t.max()) > 0.5  # the scene is not empty
    # NVRTC contracts multiply-adds differently in the two kernels: 1e-5 apart on CUDA, not 1e-6
    tol = 3e-5 if ON_CUDA else 2e-6
    np.testing.assert_allclose(img_t, img_p, atol=tol, rtol=0)
    np.testing.assert_allclose(alp_t, alp_p, atol=tol, rtol=0)
    np.testing.assert_allclose(dep_t, dep_p, atol=tol * max(1.0, float(dep_p.max())), rtol=0)
    for name, gt, gp in zip(("means", "quats", "scales", "opacities", "colors"), _grads(args, W, H, "tile"),
                            _grads(args, W, H, "pixel")):
        scale = np.abs(gp).max()
        assert np.abs(gt - gp).max() <= 1e-4 * scale, name


def test_threads_do_not_change_the_result():
    sc = _heavy_crop()
    (img1, dep1, alp1), _ = _render(sc.args[:7], sc.width, sc.height, None, threads=1)
    (img3, dep3, alp3), _ = _render(sc.args[:7], sc.width, sc.height, None, threads=3)
    np.testing.assert_array_equal(img1, img3)
    np.testing.assert_array_equal(dep1, dep3)


def test_run_options_are_checked(monkeypatch):
    sc = bench.random_scene(50, 32, 24)
    with pytest.raises(ValueError, match="composite"):
        splatsearch.rasterize(*sc.args, composite="fast")
    with pytest.raises(ValueError, match="threads"):
        splatsearch.rasterize(*sc.args, threads=0)
    from splatsearch.kernels import config

    monkeypatch.setenv(config.COMPOSITE_ENV, "pixel")
    assert config.default_composite("cpu") == "pixel"
    assert config.resolve_composite("tile", "cpu") == "tile"  # an argument beats the environment
    monkeypatch.setenv(config.COMPOSITE_ENV, "bogus")
    with pytest.raises(ValueError, match=config.COMPOSITE_ENV):
        config.default_composite("cpu")
    monkeypatch.setenv(config.THREADS_ENV, "3")
    assert config.resolve_threads(None, "cpu") == 3
    assert config.resolve_threads(2, "cpu") == 2


def test_polynomial_exp_is_accurate():
    """The compositing kernels' branch-free exp(-s) (kernels/native.py) against float64 exp: relative
    error within a few float32 ulps on the range that can give alpha >= 1/255, monotone, and so
    small past its clamp that such alphas are skipped."""
    import warp as wp

    from splatsearch.kernels.native import exp_neg
    from splatsearch.kernels.projection import ALPHA_MIN

    @wp.kernel(enable_backward=False)
    def _eval(s: wp.array(dtype=float), out: wp.array(dtype=float)):
        i = wp.tid()
        out[i] = exp_neg(s[i])

    s = np.concatenate([np.linspace(0.0, 16.0, 200_001), [20.0, 100.0, 1e30]]).astype(np.float32)
    out = wp.zeros(len(s), dtype=float, device="cpu")
    wp.launch(_eval, dim=len(s), inputs=[wp.array(s, dtype=float, device="cpu")], outputs=[out], device="cpu")
    got = out.numpy().astype(np.float64)
    ref = np.exp(-s.astype(np.float64))
    live = s <= np.log(255.0) + 1e-3
    assert np.abs(got[live] / ref[live] - 1).max() < 3e-7
    assert np.all(np.diff(got[:-3]) <= 0)
    assert np.all(0.999 * got[-3:] < ALPHA_MIN)
