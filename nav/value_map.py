"""Value and confidence maps (thesis eq 11-12), fused in JAX.

Each frame writes one scalar value ``v_t`` (eq 11: cosine of the observation and goal embeddings)
into the cells it sees, weighted by a per-cell confidence that depends on the cell's angle ``theta``
from the optical axis: ``c = cos^2(pi * theta / theta_fov)``, 1 on the axis and 0 at the edges of
the field of view. Fusion with what the cell held before is eq 12::

    v_new = (c v_t + c_prev v_prev) / (c + c_prev)
    c_new = (c^2 + c_prev^2) / (c + c_prev)

Two options come from VLFM: a confidence ``floor`` (c is mapped to [floor, 1]; VLFM uses 0.25)
and a ``gate`` (a new confidence below the gate that is also below the stored one is ignored;
VLFM uses 0.35). Both are off by default, which is the thesis' plain eq 12;
:meth:`ValueMap.vlfm` turns both on.

The fusion is a jitted function of a fixed-size square window (its side is rounded up to a
multiple of 64 cells, so only a few shapes ever compile) placed with ``lax.dynamic_update_slice``
on the donated full-size maps.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from .grid import GridSpec
from .occupancy import FovFootprint

VLFM_FLOOR = 0.25
VLFM_GATE = 0.35
R_VAL = 0.5  # m, VLFM's radius for a frontier's value
_BUCKET = 64


def confidence(theta, hfov: float, floor: float = 0.0):
    """Confidence of a cell at angle ``theta`` (rad, any shape) from the optical axis for a camera
    with horizontal field of view ``hfov`` (rad): ``cos^2(pi theta / hfov)`` inside the field of
    view, mapped to [floor, 1]; 0 outside it. Works on numpy and JAX arrays (float32)."""
    xp = jnp if isinstance(theta, jax.Array) else np
    theta = xp.asarray(theta, dtype=xp.float32)
    c = xp.cos(np.float32(np.pi) * theta / xp.float32(hfov)) ** 2
    c = xp.float32(floor) + (xp.float32(1.0) - xp.float32(floor)) * c
    return xp.where(xp.abs(theta) <= xp.float32(hfov) / 2, c, xp.float32(0.0)).astype(xp.float32)


def fuse(v_prev, c_prev, v_new, c_new, gate: float = 0.0):
    """Eq 12 for arrays of any (equal or broadcastable) shape; returns (value, confidence).

    Where ``c_new < gate`` and ``c_new < c_prev`` the new observation is ignored (VLFM's gate).
    Where both confidences are 0 the previous value and confidence are kept (no NaN).
    """
    xp = jnp if any(isinstance(a, jax.Array) for a in (v_prev, c_prev, v_new, c_new)) else np
    f32 = xp.float32
    v_prev, c_prev = xp.asarray(v_prev, dtype=f32), xp.asarray(c_prev, dtype=f32)
    v_new, c_new = xp.asarray(v_new, dtype=f32), xp.asarray(c_new, dtype=f32)
    c_new = xp.where((c_new < f32(gate)) & (c_new < c_prev), f32(0.0), c_new)
    den = c_new + c_prev
    safe = xp.where(den > 0, den, f32(1.0))
    v = xp.where(den > 0, (c_new * v_new + c_prev * v_prev) / safe, v_prev)
    c = xp.where(den > 0, (c_new * c_new + c_prev * c_prev) / safe, c_prev)
    return v.astype(f32), c.astype(f32)


@partial(jax.jit, static_argnames=("floor", "gate", "cell_size"), donate_argnums=(0, 1))
def _fuse_window(value, conf, mask, r0, c0, origin, cam_xy, cam_yaw, hfov, v_t, *, floor, gate, cell_size):
    h, w = mask.shape
    vw = jax.lax.dynamic_slice(value, (r0, c0), (h, w))
    cw = jax.lax.dynamic_slice(conf, (r0, c0), (h, w))
    f32 = jnp.float32
    ys = origin[1] + (r0 + jnp.arange(h, dtype=f32) + f32(0.5)) * f32(cell_size)
    xs = origin[0] + (c0 + jnp.arange(w, dtype=f32) + f32(0.5)) * f32(cell_size)
    theta = jnp.arctan2(ys[:, None] - cam_xy[1], xs[None, :] - cam_xy[0]) - cam_yaw
    theta = jnp.mod(theta + f32(np.pi), f32(2 * np.pi)) - f32(np.pi)
    c = jnp.where(mask, confidence(theta, hfov, floor), f32(0.0))
    v2, c2 = fuse(vw, cw, jnp.full((h, w), v_t, f32), c, gate)
    v2 = jnp.where(mask, v2, vw)
    c2 = jnp.where(mask, c2, cw)
    return (jax.lax.dynamic_update_slice(value, v2, (r0, c0)),
            jax.lax.dynamic_update_slice(conf, c2, (r0, c0)))


class ValueMap:
    """Per-cell semantic value and confidence on a :class:`GridSpec` (JAX float32 arrays).

    Args:
        spec: grid placement (share it with the occupancy grid).
        floor: confidence floor (0 = thesis; 0.25 = VLFM).
        gate: confidence gate (0 = off, thesis; 0.35 = VLFM).
    """

    def __init__(self, spec: GridSpec, *, floor: float = 0.0, gate: float = 0.0):
        if not 0.0 <= floor < 1.0:
            raise ValueError(f"floor must be in [0, 1), got {floor}")
        if not 0.0 <= gate <= 1.0:
            raise ValueError(f"gate must be in [0, 1], got {gate}")
        self.spec = spec
        self.floor = float(floor)
        self.gate = float(gate)
        self.value = jnp.zeros(spec.shape, jnp.float32)
        self.confidence = jnp.zeros(spec.shape, jnp.float32)

    @classmethod
    def vlfm(cls, spec: GridSpec) -> ValueMap:
        """VLFM's settings: confidence floor 0.25 and gate 0.35."""
        return cls(spec, floor=VLFM_FLOOR, gate=VLFM_GATE)

    def reset(self) -> None:
        self.value = jnp.zeros(self.spec.shape, jnp.float32)
        self.confidence = jnp.zeros(self.spec.shape, jnp.float32)

    def update(self, value: float, footprint: FovFootprint) -> None:
        """Write the frame value ``value`` (e.g. eq 11's cosine) into the cells ``footprint``
        marks visible, fused by eq 12 with the angle-dependent confidence."""
        v = float(value)
        if not np.isfinite(v):
            raise ValueError(f"value must be finite, got {value!r}")
        vis = np.asarray(footprint.visible, bool)
        if vis.size == 0 or not vis.any():
            return
        H, W = self.spec.shape
        r0, c0 = footprint.rows.start, footprint.cols.start
        h, w = vis.shape
        side = -(-max(h, w) // _BUCKET) * _BUCKET  # square buckets: few shapes, few compiles
        hb, wb = min(H, side), min(W, side)
        rs, cs = min(r0, H - hb), min(c0, W - wb)  # shift the window left/up to stay inside
        mask = np.zeros((hb, wb), bool)
        mask[r0 - rs:r0 - rs + h, c0 - cs:c0 - cs + w] = vis
        self.value, self.confidence = _fuse_window(
            self.value, self.confidence, jnp.asarray(mask), jnp.int32(rs), jnp.int32(cs),
            jnp.asarray(self.spec.origin_xy, jnp.float32), jnp.asarray(footprint.camera_xy, jnp.float32),
            jnp.float32(footprint.camera_yaw), jnp.float32(footprint.hfov), jnp.float32(v),
            floor=self.floor, gate=self.gate, cell_size=self.spec.cell_size)

    def scores(self, xy, radius: float = R_VAL, reduce: str = "mean") -> np.ndarray:
        """Value around each world point: (N, 2) metres -> (N,) float32.

        The ``reduce`` ("mean", default per the thesis; "median"; "max", VLFM's choice) of the
        values of the observed cells (confidence > 0) within ``radius`` m; 0 where no observed cell
        is within reach.
        """
        if reduce not in ("mean", "median", "max"):
            raise ValueError(f"reduce must be 'mean', 'median' or 'max', got {reduce!r}")
        if radius < 0:
            raise ValueError(f"radius must be >= 0, got {radius}")
        pts = np.asarray(xy, np.float64).reshape(-1, 2)
        out = np.zeros(len(pts), np.float32)
        if not len(pts):
            return out
        val = np.asarray(self.value)
        conf = np.asarray(self.confidence)
        fn = {"mean": np.mean, "median": np.median, "max": np.max}[reduce]
        for i, p in enumerate(pts):
            rows, cols, disc = self.spec.cells_within(p, radius)
            m = disc & (conf[rows, cols] > 0)
            if m.any():
                out[i] = fn(val[rows, cols][m])
        return out
