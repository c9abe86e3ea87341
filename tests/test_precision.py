"""The geometry paths trace their float32 matmuls at full precision (GPUs default to TF32)."""

import re

import jax
import jax.numpy as jnp
import numpy as np

from splatsearch.mapper import Mapper, MapperConfig, _ssim_stats_jit
from splatsearch.precision import full_precision


def _dot_lines(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if re.search(r"\bdot_general\b", ln)]


def test_full_precision_sets_highest_on_every_matmul():
    def f(a, b):
        return (a @ b).sum() + jnp.einsum("ij,jk->ik", a, b).sum()

    a = jnp.ones((3, 3), jnp.float32)
    plain = _dot_lines(jax.jit(f).lower(a, a).as_text())
    full = _dot_lines(jax.jit(full_precision(f)).lower(a, a).as_text())
    assert len(plain) == len(full) == 2
    assert not any("HIGHEST" in ln for ln in plain)
    assert all("precision = [HIGHEST, HIGHEST]" in ln for ln in full)
    assert float(jax.jit(full_precision(f))(a, a)) == float(f(a, a)) == 54.0


def test_mapper_step_runs_every_matmul_at_full_precision():
    W, H = 32, 24
    K = np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]], np.float32)
    m = Mapper(K, W, H, MapperConfig(iters=1, initial_capacity=256))
    rgb = jnp.full((H, W, 3), 0.5, jnp.float32)
    depth = jnp.full((H, W), 2.0, jnp.float32)
    stats = _ssim_stats_jit(rgb)
    text = m._step.lower(m.map.params(), m.map.active, m.opt_state, rgb, stats, depth,
                         jnp.eye(4, dtype=jnp.float32), jnp.float32(1.0)).as_text()
    dots = _dot_lines(text)
    assert dots, "the mapping loss (SSIM windows) holds matmuls"
    assert all("HIGHEST" in ln for ln in dots), [ln for ln in dots if "HIGHEST" not in ln][:3]


def test_pose_algebra_runs_at_full_precision_eagerly_and_traced():
    from splatsearch.slam import perturb_viewmat, planar_basis

    vm = jnp.eye(4, dtype=jnp.float32)
    xi = jnp.asarray([0.01, -0.02, 0.03, 0.1, 0.0, -0.1], jnp.float32)
    for fn, args in ((perturb_viewmat, (vm, xi)), (planar_basis, (vm,))):
        dots = _dot_lines(jax.jit(fn).lower(*args).as_text())
        assert dots and all("HIGHEST" in ln for ln in dots), fn.__name__
    out = np.asarray(perturb_viewmat(vm, xi))
    assert np.allclose(out[:3, 3], [0.1, 0.0, -0.1]) and np.allclose(out[:3, :3] @ out[:3, :3].T, np.eye(3), atol=1e-6)
