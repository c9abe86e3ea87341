"""Bad input gets a ValueError that names the argument, never a crash or silent NaNs."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scenes
from hypothesis import given, settings
from hypothesis import strategies as st

import splatsearch

W, H = 40, 30


def _good():
    m, q, s, o, c = scenes.random_scene(0, n=30)
    vm, _ = scenes.camera()
    return dict(means=m, quats=q, scales=s, opacities=o, colors=c, viewmat=vm, K=scenes.intrinsics(W, H),
                width=W, height=H)


def _call(**over):
    kw = _good()
    kw.update(over)
    return splatsearch.rasterize(**kw)


def _bad(name, value, match):
    with pytest.raises(ValueError, match=match):
        _call(**{name: value})


def test_good_input_renders():
    out = _call()
    assert np.isfinite(np.asarray(out.image)).all()


@pytest.mark.parametrize("name", ["means", "quats", "scales", "opacities", "colors"])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nonfinite_gaussian_values(name, bad):
    arr = np.array(_good()[name], copy=True)
    arr.reshape(-1)[3] = bad
    with pytest.raises(ValueError, match=name):
        _call(**{name: arr})


def test_nonfinite_camera():
    vm = _good()["viewmat"].copy()
    vm[0, 3] = np.nan
    _bad("viewmat", vm, "viewmat")
    K = _good()["K"].copy()
    K[0, 2] = np.inf
    _bad("K", K, "K")


def test_wrong_shapes():
    g = _good()
    _bad("means", g["means"][:, :2], "means")
    _bad("means", g["means"][None], "means")
    _bad("quats", g["quats"][:, :3], "quats")
    _bad("quats", g["quats"][:-1], "quats")
    _bad("scales", g["scales"][:, :2], "scales")
    _bad("opacities", g["opacities"][:-2], "opacities")
    _bad("colors", g["colors"][:-1], "colors")
    _bad("colors", g["colors"][:, :0], "colors")
    _bad("viewmat", np.eye(3, dtype=np.float32), "viewmat")
    _bad("K", np.eye(4, dtype=np.float32), "K")
    _bad("means", None, "means")


def test_wrong_dtypes():
    g = _good()
    _bad("means", g["means"].astype(np.int32), "means")
    _bad("colors", g["colors"] > 0.5, "colors")
    _bad("opacities", g["opacities"].astype(np.complex64), "opacities")


def test_float64_input_is_accepted():
    g = _good()
    out = _call(means=g["means"].astype(np.float64))
    ref = _call()
    np.testing.assert_allclose(np.asarray(out.image), np.asarray(ref.image), atol=1e-6)


def test_negative_scales_and_bad_ranges():
    g = _good()
    s = g["scales"].copy()
    s[2, 1] = -0.01
    _bad("scales", s, "scales")
    o = g["opacities"].copy()
    o[0] = 1.5
    _bad("opacities", o, "opacities")
    q = g["quats"].copy()
    q[1] = 0
    _bad("quats", q, "quats")


@pytest.mark.parametrize("w,h", [(0, 30), (40, 0), (-3, 30), (40.5, 30)])
def test_bad_image_size(w, h):
    with pytest.raises(ValueError, match="width|height"):
        _call(width=w, height=h)


def test_singular_or_negative_K():
    K = scenes.intrinsics(W, H)
    _bad("K", np.zeros((3, 3), np.float32), "K")
    K2 = K.copy()
    K2[0, 0] = -K2[0, 0]
    _bad("K", K2, "K")
    K3 = K.copy()
    K3[2] = [0, 0, 0]
    _bad("K", K3, "K")


def test_bad_render_mode_and_planes():
    with pytest.raises(ValueError, match="render_mode"):
        _call(render_mode="RGBA")
    with pytest.raises(ValueError, match="near_plane"):
        _call(near_plane=0.0)


def test_values_checked_on_device_under_jit(capfd):
    """Under jit the values are tracers; the device-side check reports the same message, and it
    is the first thing printed: no Warp callback traceback before it."""
    g = _good()
    f = jax.jit(lambda m: splatsearch.rasterize(m, g["quats"], g["scales"], g["opacities"], g["colors"],
                                                g["viewmat"], g["K"], W, H).image)
    m = g["means"].copy()
    assert np.isfinite(np.asarray(f(m))).all()
    m[5, 0] = np.nan
    capfd.readouterr()
    with pytest.raises(Exception, match="means contains NaN or Inf"):
        jax.block_until_ready(f(m))
    printed = capfd.readouterr()
    assert "Traceback" not in printed.out + printed.err
    fs = jax.jit(lambda s: splatsearch.rasterize(g["means"], g["quats"], s, g["opacities"], g["colors"],
                                                 g["viewmat"], g["K"], W, H).image)
    s = g["scales"].copy()
    s[0, 0] = -1
    with pytest.raises(Exception, match="scales must be non-negative"):
        jax.block_until_ready(fs(s))
    # a good call afterwards still works: nothing was left in a broken state
    assert np.isfinite(np.asarray(f(g["means"]))).all()


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**16), n=st.integers(0, 40), scale_exp=st.floats(-4, 0.5))
def test_random_valid_scenes_never_produce_nan(seed, n, scale_exp):
    """Any valid input (including extreme scales and empty scenes) gives finite outputs and grads."""
    rng = np.random.default_rng(seed)
    m = rng.normal(0, 1.5, (n, 3)).astype(np.float32)
    q = rng.normal(size=(n, 4)).astype(np.float32) + np.array([1e-3, 0, 0, 0], np.float32)
    s = (10.0 ** scale_exp * rng.uniform(0.1, 1, (n, 3))).astype(np.float32)
    o = rng.uniform(0, 1, n).astype(np.float32)
    c = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    vm, _ = scenes.camera()
    K = scenes.intrinsics(W, H)

    def loss(m, s):
        out = splatsearch.rasterize(m, q, s, o, c, vm, K, W, H, render_mode="RGB+ED")
        return jnp.sum(out.image) + jnp.sum(out.depth) + jnp.sum(out.alpha)

    val, (gm, gs) = jax.value_and_grad(loss, argnums=(0, 1))(m, s)
    assert np.isfinite(float(val))
    assert np.isfinite(np.asarray(gm)).all() and np.isfinite(np.asarray(gs)).all()


def test_process_default_threads_come_before_the_environment(monkeypatch):
    from splatsearch.kernels import config

    monkeypatch.setenv(config.THREADS_ENV, "3")
    try:
        assert config.default_threads() == 3
        config.set_default_threads(1)
        assert config.default_threads() == 1
        with pytest.raises(ValueError):
            config.set_default_threads(0)
    finally:
        config.set_default_threads(None)
    assert config.default_threads() == 3
