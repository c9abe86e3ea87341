"""Benchmark scenes and timing helpers for the rasterizer (used by ``splatsearch bench`` and
``benchmarks/``).

The *profile scene* is the one the rasterizer targets are stated on: 111,785 Gaussians sampled
on the surfaces of a procedural room (floor, ceiling, four walls and a few furniture boxes), scales
U[1e-4, 0.02] m, random unit quaternions, opacities U[0, 1], seen at 648x420 from inside the room.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

PROFILE_N = 111_785
PROFILE_W, PROFILE_H = 648, 420


@dataclass
class Scene:
    """Gaussian parameters (float32 numpy) plus one camera."""

    means: np.ndarray  # (N, 3) m
    quats: np.ndarray  # (N, 4) wxyz, unit
    scales: np.ndarray  # (N, 3) m
    opacities: np.ndarray  # (N,)
    colors: np.ndarray  # (N, 3) in [0, 1]
    viewmat: np.ndarray  # (4, 4) world-to-camera
    K: np.ndarray  # (3, 3)
    width: int
    height: int

    @property
    def args(self) -> tuple:
        return (self.means, self.quats, self.scales, self.opacities, self.colors, self.viewmat, self.K,
                self.width, self.height)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World-to-camera 4x4 (OpenCV frame) of a camera at ``eye`` looking at ``target``; world z up."""
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    vm = np.eye(4)
    vm[:3, :3] = np.stack([x, y, z])
    vm[:3, 3] = -vm[:3, :3] @ eye
    return vm.astype(np.float32)


def intrinsics_from_hfov(width: int, height: int, hfov_deg: float) -> np.ndarray:
    """Pinhole K (3x3, pixels) with square pixels and the principal point at the image centre."""
    f = 0.5 * width / np.tan(np.radians(hfov_deg) / 2)
    return np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], np.float32)


def _room_quads(rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """(origin, edge_u, edge_v, base colour) of every sampled rectangle of the room."""
    L, Wd, Hh = 6.0, 4.5, 2.6
    quads = [
        (np.array([0, 0, 0.0]), np.array([L, 0, 0]), np.array([0, Wd, 0]), np.array([0.55, 0.45, 0.35])),  # floor
        (np.array([0, 0, Hh]), np.array([L, 0, 0]), np.array([0, Wd, 0]), np.array([0.9, 0.9, 0.88])),  # ceiling
        (np.array([0, 0, 0.0]), np.array([L, 0, 0]), np.array([0, 0, Hh]), np.array([0.7, 0.75, 0.8])),
        (np.array([0, Wd, 0.0]), np.array([L, 0, 0]), np.array([0, 0, Hh]), np.array([0.8, 0.7, 0.6])),
        (np.array([0, 0, 0.0]), np.array([0, Wd, 0]), np.array([0, 0, Hh]), np.array([0.6, 0.8, 0.6])),
        (np.array([L, 0, 0.0]), np.array([0, Wd, 0]), np.array([0, 0, Hh]), np.array([0.75, 0.65, 0.8])),
    ]
    for _ in range(6):  # furniture boxes: five visible faces each
        c = np.array([rng.uniform(0.6, L - 0.6), rng.uniform(0.6, Wd - 0.6), 0.0])
        sx, sy, sz = rng.uniform(0.3, 1.0), rng.uniform(0.3, 1.0), rng.uniform(0.4, 1.2)
        col = rng.uniform(0.1, 0.9, 3)
        o = c - np.array([sx, sy, 0]) / 2
        quads += [
            (o + [0, 0, sz], np.array([sx, 0, 0]), np.array([0, sy, 0]), col),
            (o, np.array([sx, 0, 0]), np.array([0, 0, sz]), col * 0.9),
            (o + [0, sy, 0], np.array([sx, 0, 0]), np.array([0, 0, sz]), col * 0.9),
            (o, np.array([0, sy, 0]), np.array([0, 0, sz]), col * 0.8),
            (o + [sx, 0, 0], np.array([0, sy, 0]), np.array([0, 0, sz]), col * 0.8),
        ]
    return quads


def profile_scene(n: int = PROFILE_N, width: int = PROFILE_W, height: int = PROFILE_H, seed: int = 0) -> Scene:
    """The rasterizer's profile scene (see module docstring); deterministic per seed."""
    rng = np.random.default_rng(seed)
    quads = _room_quads(rng)
    areas = np.array([np.linalg.norm(np.cross(u, v)) for _, u, v, _ in quads])
    which = rng.choice(len(quads), size=n, p=areas / areas.sum())
    a, b = rng.uniform(0, 1, (2, n))
    origin = np.stack([quads[k][0] for k in which])
    eu = np.stack([quads[k][1] for k in which])
    ev = np.stack([quads[k][2] for k in which])
    base = np.stack([quads[k][3] for k in which])
    means = origin + a[:, None] * eu + b[:, None] * ev
    # procedural texture: checker + noise so that colours vary over each surface
    checker = ((np.floor(means[:, 0] * 4) + np.floor(means[:, 1] * 4) + np.floor(means[:, 2] * 4)) % 2)[:, None]
    colors = np.clip(base * (0.75 + 0.25 * checker) + rng.normal(0, 0.05, (n, 3)), 0, 1)
    quats = rng.normal(size=(n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    scales = rng.uniform(1e-4, 0.02, (n, 3))
    opac = rng.uniform(0, 1, n)
    vm = look_at([1.0, 1.0, 1.3], [5.0, 3.2, 0.9])
    K = intrinsics_from_hfov(width, height, 79.0)
    f32 = lambda x: np.ascontiguousarray(x, np.float32)  # noqa: E731
    return Scene(f32(means), f32(quats), f32(scales), f32(opac), f32(colors), vm, K, width, height)


def random_scene(n: int = 10_000, width: int = 320, height: int = 240, seed: int = 0) -> Scene:
    """n Gaussians in a 4 m cube in front of a camera: benchmark (b) of the rasterizer issue."""
    rng = np.random.default_rng(seed)
    means = rng.uniform(-2, 2, (n, 3)) + np.array([0, 0, 4.0])
    quats = rng.normal(size=(n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    scales = rng.uniform(0.005, 0.05, (n, 3))
    f32 = lambda x: np.ascontiguousarray(x, np.float32)  # noqa: E731
    return Scene(f32(means), f32(quats), f32(scales), f32(rng.uniform(0, 1, n)), f32(rng.uniform(0, 1, (n, 3))),
                 np.eye(4, dtype=np.float32), intrinsics_from_hfov(width, height, 79.0), width, height)


def count_gaussian_pixel_evaluations(scene: Scene) -> int:
    """Exact number of Gaussian-pixel evaluations one forward compositing pass performs."""
    import warp as wp

    from splatsearch.kernels import pipeline as pl

    dev = "cpu"
    n = scene.means.shape[0]
    arr = lambda x, dt: wp.array(x, dtype=dt, device=dev)  # noqa: E731
    means2d = wp.empty(n, dtype=wp.vec2, device=dev)
    conics = wp.empty(n, dtype=wp.vec3, device=dev)
    depths = wp.empty(n, dtype=wp.float32, device=dev)
    radii = wp.empty(n, dtype=wp.vec2i, device=dev)
    opac = arr(scene.opacities, wp.float32)
    pl.project(arr(scene.means, wp.vec3), arr(scene.quats, wp.vec4), arr(scene.scales, wp.vec3), opac,
               arr(scene.viewmat[None], wp.mat44), arr(scene.K[None], wp.mat33), scene.width, scene.height,
               0.01, 1e10, 0.3, means2d, conics, depths, radii)
    ws = pl.Workspace(dev)
    ranges, ids, _ = pl.bin_gaussians(ws, means2d, conics, opac, depths, radii, scene.width, scene.height)
    return pl.count_evaluations(means2d, conics, opac, ranges, ids, scene.width, scene.height)


def time_call(fn, repeats: int = 5, warmup: int = 2) -> tuple[float, float]:
    """(median, min) wall seconds of ``fn()``, which must block until its result is ready."""
    for _ in range(warmup):
        fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts)), float(np.min(ts))


#: the box's 2-core AVX2 ceiling for forward Gaussian-pixel evaluations (see DESIGN.md)
CPU_PEAK_EVALS_PER_S = 5.0e9


@dataclass
class BenchResult:
    name: str
    n: int
    width: int
    height: int
    n_isect: int
    evals: int
    fwd_s: float
    fwd_bwd_s: float

    @property
    def evals_per_s(self) -> float:
        return self.evals / self.fwd_s

    @property
    def peak_fraction(self) -> float:
        return self.evals_per_s / CPU_PEAK_EVALS_PER_S


def make_render_fns(scene: Scene):
    """Jitted ``forward(*params)`` and ``forward+backward(*params)`` on ``scene`` (RGB+D)."""
    import jax
    import jax.numpy as jnp

    from splatsearch.rasterization import rasterize

    W, H = scene.width, scene.height

    def fwd(m, q, s, o, c, vm, K):
        out = rasterize(m, q, s, o, c, vm, K, W, H, render_mode="RGB+D")
        return out.image, out.depth, out.alpha

    def loss(m, q, s, o, c, vm, K):
        img, dep, alp = fwd(m, q, s, o, c, vm, K)
        return jnp.mean(img) + 0.1 * jnp.mean(dep) + jnp.mean(alp)

    params = tuple(jnp.asarray(a) for a in scene.args[:7])
    return jax.jit(fwd), jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2, 3, 4, 5))), params


def run_benchmark(scene: Scene, name: str, repeats: int = 5) -> BenchResult:
    """Time forward and forward+backward of ``scene`` (median of ``repeats`` after warm-up)."""
    import jax

    from splatsearch.rasterization import rasterize

    fwd, fwd_bwd, params = make_render_fns(scene)
    t_f, _ = time_call(lambda: jax.block_until_ready(fwd(*params)), repeats)
    t_fb, _ = time_call(lambda: jax.block_until_ready(fwd_bwd(*params)), repeats)
    n_isect = int(rasterize(*params, scene.width, scene.height).meta["n_isect"])
    return BenchResult(name, scene.means.shape[0], scene.width, scene.height, n_isect,
                       count_gaussian_pixel_evaluations(scene), t_f, t_fb)
