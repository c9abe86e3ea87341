"""GaussianMap: a capacity-padded pytree of 3-D Gaussians with an active mask.

Parameters are stored unconstrained: log scales, opacity logits, raw quaternions (normalised by
the rasterizer) and RGB colours (clipped to [0, 1] when rendered). Inactive slots render with
zero opacity, so they are culled in the projection and receive no gradient. Capacity grows
geometrically (x2), so a jitted step recompiles about log2(N) times over a run.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

PARAM_NAMES = ("means", "log_scales", "quats", "opacity_logits", "colors")


@dataclass
class GaussianMap:
    """means (C, 3) m; log_scales (C, 3) or (C, 1) if isotropic; quats (C, 4) wxyz;
    opacity_logits (C,); colors (C, 3); active (C,) bool. ``isotropic`` is static."""

    means: jax.Array
    log_scales: jax.Array
    quats: jax.Array
    opacity_logits: jax.Array
    colors: jax.Array
    active: jax.Array
    isotropic: bool = field(default=False, metadata=dict(static=True))

    @property
    def capacity(self) -> int:
        return int(self.means.shape[0])

    @property
    def n_active(self) -> int:
        return int(np.asarray(self.active).sum())

    def params(self) -> dict[str, jax.Array]:
        return {k: getattr(self, k) for k in PARAM_NAMES}

    def replace(self, **kw) -> GaussianMap:
        return dataclasses.replace(self, **kw)

    def with_params(self, params: dict) -> GaussianMap:
        return self.replace(**params)

    def render_args(self) -> tuple:
        """(means, quats, scales, opacities, colors) for :func:`splatsearch.rasterize`."""
        return render_args(self.params(), self.active, self.isotropic)


jax.tree_util.register_dataclass(GaussianMap, data_fields=list(PARAM_NAMES) + ["active"], meta_fields=["isotropic"])


def render_args(params: dict, active, isotropic: bool) -> tuple:
    """Constrained rasterizer inputs from unconstrained parameters; inactive slots get opacity 0."""
    scales = jnp.exp(params["log_scales"])
    if isotropic:
        scales = jnp.broadcast_to(scales.reshape(-1, 1), (scales.shape[0], 3))
    opac = jax.nn.sigmoid(params["opacity_logits"]) * active.astype(jnp.float32)
    return params["means"], params["quats"], scales, opac, jnp.clip(params["colors"], 0.0, 1.0)


def empty_map(capacity: int = 1024, isotropic: bool = False) -> GaussianMap:
    """An empty map with room for ``capacity`` Gaussians."""
    if capacity < 1:
        raise ValueError(f"capacity must be >= 1, got {capacity}")
    c = int(capacity)
    q = np.zeros((c, 4), np.float32)
    q[:, 0] = 1
    return GaussianMap(
        means=jnp.zeros((c, 3), jnp.float32), log_scales=jnp.full((c, 1 if isotropic else 3), -5.0, jnp.float32),
        quats=jnp.asarray(q), opacity_logits=jnp.full((c,), -20.0, jnp.float32), colors=jnp.zeros((c, 3), jnp.float32),
        active=jnp.zeros((c,), bool), isotropic=isotropic)


# Host-side (numpy) edits: shapes such as "n new Gaussians" change every frame, and eager jnp
# scatters would compile a new XLA program for each of them.

def _np_tree(tree):
    return jax.tree_util.tree_map(lambda x: np.array(x) if hasattr(x, "shape") else x, tree)


def _jnp_tree(tree):
    return jax.tree_util.tree_map(lambda x: jnp.asarray(x) if isinstance(x, np.ndarray) else x, tree)


def _map_rows(tree, cap: int, fn):
    """Apply ``fn`` to every array leaf whose leading dimension is the capacity."""
    return jax.tree_util.tree_map(lambda x: fn(x) if isinstance(x, np.ndarray) and x.ndim >= 1
                                  and x.shape[0] == cap else x, tree)


def _fields(gmap: GaussianMap) -> dict:
    return {k: np.array(getattr(gmap, k)) for k in PARAM_NAMES + ("active",)}


def grow(gmap: GaussianMap, opt_state, needed: int):
    """Return (map, opt_state) with capacity >= ``needed`` (doubling); new slots are empty and
    their optimiser moments zero, so the optimiser state stays consistent with the parameters."""
    old = gmap.capacity
    if needed <= old:
        return gmap, opt_state
    new = old
    while new < needed:
        new *= 2
    fresh = _fields(empty_map(new - old, gmap.isotropic))
    cur = _fields(gmap)
    gmap = gmap.replace(**{k: jnp.asarray(np.concatenate([cur[k], fresh[k]], 0)) for k in cur})
    if opt_state is not None:
        opt_state = _jnp_tree(_map_rows(_np_tree(opt_state), old, lambda x: np.concatenate(
            [x, np.zeros((new - old,) + x.shape[1:], x.dtype)], 0)))
    return gmap, opt_state


def append(gmap: GaussianMap, opt_state, new: dict):
    """Append Gaussians given as numpy arrays (means (n,3), log_scales, quats, opacity_logits,
    colors); grows the capacity when needed. Returns (map, opt_state, indices)."""
    n_new = int(np.asarray(new["means"]).shape[0])
    n = gmap.n_active
    gmap, opt_state = grow(gmap, opt_state, n + n_new)
    if n_new == 0:
        return gmap, opt_state, np.zeros(0, np.int64)
    # active Gaussians are kept compact at the front (see ``compact``)
    idx = np.arange(n, n + n_new)
    cur = _fields(gmap)
    for k in PARAM_NAMES:
        v = np.asarray(new[k], np.float32)
        if k == "log_scales" and gmap.isotropic and v.ndim == 2 and v.shape[1] == 3:
            v = v.mean(1, keepdims=True)
        cur[k][idx] = v.reshape((n_new,) + cur[k].shape[1:])
    cur["active"][idx] = True
    if opt_state is not None:
        def zero(x):
            x[idx] = 0
            return x

        opt_state = _jnp_tree(_map_rows(_np_tree(opt_state), gmap.capacity, zero))
    return gmap.replace(**{k: jnp.asarray(v) for k, v in cur.items()}), opt_state, idx


def compact(gmap: GaussianMap, opt_state, keep: np.ndarray):
    """Keep only the slots where ``keep`` (C,) is True, moved to the front in order; the rest
    become empty. Capacity is unchanged, so jitted steps are not recompiled."""
    keep = np.asarray(keep, bool) & np.asarray(gmap.active)
    cap = gmap.capacity
    order = np.r_[np.flatnonzero(keep), np.flatnonzero(~keep)]
    n = int(keep.sum())
    fresh = _fields(empty_map(cap, gmap.isotropic))
    cur = _fields(gmap)
    out = {}
    for k in PARAM_NAMES + ("active",):
        v = cur[k][order]
        v[n:] = fresh[k][n:]
        out[k] = jnp.asarray(v)

    def perm(x):
        x = x[order]
        x[n:] = 0
        return x

    if opt_state is not None:
        opt_state = _jnp_tree(_map_rows(_np_tree(opt_state), cap, perm))
    return gmap.replace(**out), opt_state
