"""Hand-written Warp backward against jax.grad of the dense float64 reference, plus finite differences."""

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
NAMES = ["means", "quats", "scales", "opacities", "colors", "viewmat"]


def _weights(seed, C=3):
    rng = np.random.default_rng(100 + seed)
    return (rng.uniform(-1, 1, (H, W, C)), rng.uniform(-1, 1, (H, W, 1)) * 0.3, rng.uniform(-1, 1, (H, W, 1)))


def _loss_ours(wc, wd, wa, mode="RGB+D", bg=None):
    def f(means, quats, scales, opacities, colors, viewmat, K):
        out = splatsearch.rasterize(means, quats, scales, opacities, colors, viewmat, K, W, H,
                                    render_mode=mode, backgrounds=bg)
        return jnp.sum(out.image * wc) + jnp.sum(out.depth * wd) + jnp.sum(out.alpha * wa)
    return f


def _loss_ref(wc, wd, wa, mode="RGB+D", bg=None):
    def f(means, quats, scales, opacities, colors, viewmat, K):
        color, depth, alpha, _ = reference.rasterize_dense(means, quats, scales, opacities, colors, viewmat, K, W, H)
        if bg is not None:
            color = color + (1 - alpha) * bg
        if mode.endswith("ED"):
            depth = depth / jnp.maximum(alpha, 1e-10)
        return jnp.sum(color * wc) + jnp.sum(depth * wd) + jnp.sum(alpha * wa)
    return f


def _compare(g_ours, g_ref, name, rel=1e-3):
    a = np.asarray(g_ours, np.float64)
    b = np.asarray(g_ref, np.float64)
    assert a.shape == b.shape, name
    assert np.all(np.isfinite(a)), name
    scale = np.abs(b).max(initial=0.0)
    if scale == 0:
        assert np.abs(a).max(initial=0.0) == 0, name
        return
    err = np.abs(a - b).max()
    assert err <= rel * scale, f"{name}: max |diff| {err:.3g} vs max |ref| {scale:.3g}"


@functools.cache
def _ref_grads(kind, seed=0, mode="RGB+D", bg=None):
    """jax.grad of the float64 reference, jitted (one XLA program compiles far faster than the
    eager op-by-op trace of the dense reference) and shared by both rasterizer variants."""
    params = scenes.scene(kind, seed)
    vm, K = scenes.camera()
    wc, wd, wa = _weights(seed)
    bg = None if bg is None else jnp.asarray(bg)
    args64 = [jnp.asarray(a, jnp.float64) for a in (*params, vm, K)]
    return jax.jit(jax.grad(_loss_ref(wc, wd, wa, mode, bg), argnums=tuple(range(6))))(*args64)


def _grads(kind, seed=0, mode="RGB+D", bg=None):
    params = scenes.scene(kind, seed)
    vm, K = scenes.camera()
    wc, wd, wa = _weights(seed)
    args32 = [jnp.asarray(a) for a in params] + [jnp.asarray(vm), jnp.asarray(K)]
    g_ours = jax.grad(_loss_ours(wc, wd, wa, mode, None if bg is None else jnp.asarray(bg)),
                      argnums=tuple(range(6)))(*args32)
    return g_ours, _ref_grads(kind, seed, mode, bg)


@pytest.mark.parametrize("kind", ["random", "single", "straddle", "full_frame", "subpixel", "behind", "near_plane"])
def test_grad_matches_reference(kind, variant):
    g_ours, g_ref = _grads(kind)
    for name, a, b in zip(NAMES, g_ours, g_ref):
        _compare(a, b, f"{kind}/{name}")


def test_grad_expected_depth_and_background():
    g_ours, g_ref = _grads("random", seed=2, mode="RGB+ED", bg=(0.3, 0.1, 0.8))
    for name, a, b in zip(NAMES, g_ours, g_ref):
        _compare(a, b, f"ED+bg/{name}")


def test_grad_empty_scene_is_zero():
    params = scenes.scene("empty")
    vm, K = scenes.camera()
    wc, wd, wa = _weights(0)
    g = jax.grad(_loss_ours(wc, wd, wa), argnums=(0, 5))(*params, vm, K)
    assert g[0].shape == (0, 3)
    assert float(jnp.abs(g[1]).max()) == 0.0


def test_grad_under_jit_and_repeated():
    params = scenes.scene("random", seed=9)
    vm, K = scenes.camera()
    wc, wd, wa = _weights(9)
    gfun = jax.jit(jax.grad(_loss_ours(wc, wd, wa), argnums=(0, 2, 5)))
    g1 = gfun(*params, vm, K)
    g2 = gfun(*params, vm, K)
    for a, b in zip(g1, g2):
        if ON_CUDA:  # the CUDA backward sums with atomics: repeatable to rounding, not bitwise
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-6)
        else:  # CPU sums in a fixed order: bitwise
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    g_ref = jax.jit(jax.grad(_loss_ref(wc, wd, wa), argnums=(0, 2, 5)))(
        *[jnp.asarray(a, jnp.float64) for a in (*params, vm, K)])
    for name, a, b in zip(["means", "scales", "viewmat"], g1, g_ref):
        _compare(a, b, name)


def test_grad_when_binning_slot_was_reused():
    """Many forwards before the backward force the backward to re-bin; the result must not change."""
    params = scenes.scene("random", seed=11)
    vm, K = scenes.camera()
    wc, wd, wa = _weights(11)

    def many(means):
        total = 0.0
        for k in range(12):  # more renders than binning slots
            total = total + _loss_ours(wc, wd, wa)(means * (1.0 + 1e-3 * k), *params[1:], vm, K)
        return total

    g = jax.grad(many)(jnp.asarray(params[0]))
    rest = [jnp.asarray(a, jnp.float64) for a in (*params[1:], vm, K)]
    factors = 1.0 + 1e-3 * jnp.arange(12, dtype=jnp.float64)
    ref_total = lambda m: jnp.sum(jax.vmap(lambda s: _loss_ref(wc, wd, wa)(m * s, *rest))(factors))
    g_ref = jax.jit(jax.grad(ref_total))(jnp.asarray(params[0], jnp.float64))
    _compare(g, g_ref, "means")


def test_reference_grad_matches_finite_differences():
    """The float64 oracle itself is checked by central differences."""
    params = scenes.scene("random", seed=1)
    vm, K = scenes.camera()
    wc, wd, wa = _weights(1)
    args = [jnp.asarray(a, jnp.float64) for a in (*params, vm, K)]
    f = jax.jit(_loss_ref(wc, wd, wa))
    grads = jax.jit(jax.grad(f, argnums=tuple(range(6))))(*args)
    rng = np.random.default_rng(0)
    for which in range(6):
        g = np.asarray(grads[which])
        flat = np.flatnonzero(np.abs(g) > 1e-3 * np.abs(g).max())
        for idx in rng.choice(flat, size=min(3, len(flat)), replace=False):
            eps = 1e-6
            plus = [a for a in args]
            minus = [a for a in args]
            plus[which] = args[which].ravel().at[idx].add(eps).reshape(args[which].shape)
            minus[which] = args[which].ravel().at[idx].add(-eps).reshape(args[which].shape)
            fd = (float(f(*plus)) - float(f(*minus))) / (2 * eps)
            assert abs(fd - g.ravel()[idx]) <= 1e-4 * max(1.0, abs(fd)), (NAMES[which], idx, fd, g.ravel()[idx])


def test_ours_matches_finite_differences():
    """Central differences on the float32 Warp rasterizer itself, for a few parameters.

    The 1/255 alpha cut-off makes the image discontinuous at the Gaussian's rim, so the loss
    weights are zero there: differences then see only the smooth core.
    """
    params = [np.asarray(a, np.float32) for a in scenes.scene("single", 0)]
    vm, K = scenes.camera()
    wc, wd, wa = _weights(3)
    core = np.asarray(splatsearch.rasterize(*params, vm, K, W, H).alpha) > 0.05
    assert core.sum() > 20
    wc, wd, wa = wc * core, wd * core, wa * core
    f = _loss_ours(wc, wd, wa)
    args = [jnp.asarray(a) for a in (*params, vm, K)]
    grads = jax.grad(f, argnums=tuple(range(6)))(*args)
    checks = [(0, 0, 1e-3), (0, 2, 1e-3), (2, 1, 1e-3), (3, 0, 1e-3), (4, 1, 1e-2), (1, 2, 1e-3), (5, 3, 1e-3), (5, 5, 1e-3)]
    for which, idx, eps in checks:
        base = np.asarray(args[which], np.float64)
        plus, minus = base.copy().ravel(), base.copy().ravel()
        plus[idx] += eps
        minus[idx] -= eps
        a_p = list(args)
        a_m = list(args)
        a_p[which] = jnp.asarray(plus.reshape(base.shape), jnp.float32)
        a_m[which] = jnp.asarray(minus.reshape(base.shape), jnp.float32)
        fd = (float(f(*a_p)) - float(f(*a_m))) / (2 * eps)
        an = float(np.asarray(grads[which]).ravel()[idx])
        assert abs(fd - an) <= 2e-2 * max(abs(fd), abs(an), 1e-2), (NAMES[which], idx, fd, an)
