"""The pose-only backward (``rasterize(..., differentiable="viewmat")``) against the full backward
and jax.grad of the dense float64 reference; its thread-count independence on the CPU."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference
import scenes
from scenes import ON_CUDA

import splatsearch

W, H = scenes.W, scenes.H


def _weights(seed, width=W, height=H, keep=0.6):
    """Random cotangents of colour, depth and alpha, zero outside a random mask (as a loss mask)."""
    rng = np.random.default_rng(200 + seed)
    mask = rng.uniform(size=(height, width, 1)) < keep
    return (rng.uniform(-1, 1, (height, width, 3)) * mask, rng.uniform(-1, 1, (height, width, 1)) * 0.3 * mask,
            rng.uniform(-1, 1, (height, width, 1)) * mask)


def _loss(params, K, weights, diff, width=W, height=H, **kw):
    wc, wd, wa = weights

    def f(vm):
        out = splatsearch.rasterize(*params, vm, K, width, height, differentiable=diff, **kw)
        return jnp.sum(out.image * wc) + jnp.sum(out.depth * wd) + jnp.sum(out.alpha * wa)
    return f


@functools.cache
def _ref_grad(kind, seed):
    params = scenes.scene(kind, seed)
    vm, K = scenes.camera()
    wc, wd, wa = _weights(seed)

    def f(means, quats, scales, opacities, colors, viewmat, K):
        color, depth, alpha, _ = reference.rasterize_dense(means, quats, scales, opacities, colors, viewmat, K, W, H)
        return jnp.sum(color * wc) + jnp.sum(depth * wd) + jnp.sum(alpha * wa)

    args64 = [jnp.asarray(a, jnp.float64) for a in (*params, vm, K)]
    return np.asarray(jax.jit(jax.grad(f, argnums=5))(*args64))


CASES = [("random", 0), ("random", 1), ("random", 4), ("straddle", 0), ("full_frame", 0), ("behind", 0),
         ("near_plane", 0)]


@pytest.mark.parametrize("kind,seed", CASES)
def test_pose_grad_matches_full_backward_and_reference(kind, seed, variant):
    params = scenes.scene(kind, seed)
    vm, K = scenes.camera()
    w = _weights(seed)
    g_pose = np.asarray(jax.grad(_loss(params, K, w, "viewmat"))(jnp.asarray(vm)), np.float64)
    g_all = np.asarray(jax.grad(_loss(params, K, w, "all"))(jnp.asarray(vm)), np.float64)
    scale = np.abs(g_all).max()
    assert scale > 0 and np.all(np.isfinite(g_pose))
    # the same float32 terms, summed in another order
    assert np.abs(g_pose - g_all).max() <= 2e-5 * scale, (g_pose, g_all)
    g_ref = _ref_grad(kind, seed)
    assert np.abs(g_pose - g_ref).max() <= 1e-3 * np.abs(g_ref).max(), (g_pose, g_ref)
    assert np.all(g_pose[3] == 0)


def test_gaussians_are_constants_in_pose_mode():
    params = [jnp.asarray(a) for a in scenes.scene("random", 2)]
    vm, K = scenes.camera()
    wc, wd, wa = _weights(2)

    def f(means, colors, vm, diff):
        out = splatsearch.rasterize(means, params[1], params[2], params[3], colors, vm, K, W, H, differentiable=diff)
        return jnp.sum(out.image * wc) + jnp.sum(out.depth * wd) + jnp.sum(out.alpha * wa)

    gm, gc, gv = jax.grad(f, argnums=(0, 1, 2))(params[0], params[4], jnp.asarray(vm), "viewmat")
    assert float(jnp.abs(gm).max()) == 0.0 and float(jnp.abs(gc).max()) == 0.0
    gv_all = jax.grad(f, argnums=2)(params[0], params[4], jnp.asarray(vm), "all")
    np.testing.assert_allclose(np.asarray(gv), np.asarray(gv_all), rtol=0, atol=2e-5 * float(jnp.abs(gv_all).max()))


def test_pose_grad_of_masked_out_pixels_is_zero():
    params = scenes.scene("random", 0)
    vm, K = scenes.camera()
    zero = (np.zeros((H, W, 3)), np.zeros((H, W, 1)), np.zeros((H, W, 1)))
    g = jax.grad(_loss(params, K, zero, "viewmat"))(jnp.asarray(vm))
    assert float(jnp.abs(g).max()) == 0.0


def test_pose_grad_empty_scene_and_batched_cameras():
    vm, K = scenes.camera()
    empty = scenes.scene("empty")
    g = jax.grad(_loss(empty, K, _weights(0), "viewmat"))(jnp.asarray(vm))
    assert g.shape == (4, 4) and float(jnp.abs(g).max()) == 0.0
    params = scenes.scene("random", 3)
    vm2 = np.stack([vm, vm @ np.diag([1.0, 1.0, 1.0, 1.0]).astype(np.float32)])
    vm2[1, 0, 3] += 0.05
    w = _weights(3)
    w2 = tuple(np.stack([x, x[::-1]]) for x in w)
    gb = {d: np.asarray(jax.grad(_loss(params, K, w2, d))(jnp.asarray(vm2))) for d in ("viewmat", "all")}
    assert gb["viewmat"].shape == (2, 4, 4)
    assert np.abs(gb["viewmat"] - gb["all"]).max() <= 2e-5 * np.abs(gb["all"]).max()


def test_bad_differentiable_is_refused():
    params = scenes.scene("random", 0)
    vm, K = scenes.camera()
    with pytest.raises(ValueError, match="differentiable"):
        splatsearch.rasterize(*params, vm, K, W, H, differentiable="pose")


@pytest.mark.parametrize("composite", ["tile", "pixel"])
def test_pose_grad_is_bitwise_independent_of_threads(composite):
    if ON_CUDA:
        pytest.skip("threads are a CPU option; the CUDA backward sums with atomics")
    # several tile rows (the accumulator groups) and several 256-Gaussian chunks
    width, height = 160, 120
    K = scenes.intrinsics(width, height, 110.0)
    vm = scenes.look_at([0.3, -3.0, 0.4], [0.0, 0.0, 0.0])
    params = scenes.random_scene(7, 3000)
    w = _weights(7, width, height)
    gs = [np.asarray(jax.grad(_loss(params, K, w, "viewmat", width, height, composite=composite, threads=t))(
        jnp.asarray(vm))) for t in (1, 2, 3, 5)]
    assert np.abs(gs[0]).max() > 0
    for g in gs[1:]:
        np.testing.assert_array_equal(g, gs[0])
