"""Benchmark scenes and timing helpers for the rasterizer (used by ``splatsearch bench`` and
``benchmarks/``).

Scenes (the letters of the rasterizer-speed issue):

* (a) ``profile``: 111,785 Gaussians sampled on the surfaces of a procedural room (floor, ceiling,
  four walls and a few furniture boxes), scales U[1e-4, 0.02] m, random unit quaternions,
  opacities U[0, 1], seen at 648x420 from inside the room;
* (b) ``heavy``: the same room with scales U[5e-4, 0.1] m, the overlap a mapped interior has
  (about 3.5x the tile intersections of (a));
* (c) ``house``: the map the mapper builds of simulator house 0 (a development house) from the
  first 40 frames of its walk, rendered from the walk's poses at 320x240 and 640x480; built once
  and cached (see :func:`house_map`);
* (d) ``random10k``: 10k random Gaussians in a 4 m cube at 320x240.
"""

from __future__ import annotations

import time
from collections.abc import Callable
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


def profile_scene(n: int = PROFILE_N, width: int = PROFILE_W, height: int = PROFILE_H, seed: int = 0,
                  scale_range: tuple[float, float] = (1e-4, 0.02)) -> Scene:
    """The rasterizer's profile scene (see module docstring); deterministic per seed.
    ``scale_range`` (m): bounds of the uniform per-axis scales."""
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
    scales = rng.uniform(scale_range[0], scale_range[1], (n, 3))
    opac = rng.uniform(0, 1, n)
    vm = look_at([1.0, 1.0, 1.3], [5.0, 3.2, 0.9])
    K = intrinsics_from_hfov(width, height, 79.0)
    f32 = lambda x: np.ascontiguousarray(x, np.float32)  # noqa: E731
    return Scene(f32(means), f32(quats), f32(scales), f32(opac), f32(colors), vm, K, width, height)


def heavy_scene(width: int = PROFILE_W, height: int = PROFILE_H, seed: int = 0) -> Scene:
    """Scene (b): the profile room with realistic, overlapping scales U[5e-4, 0.1] m."""
    return profile_scene(PROFILE_N, width, height, seed, scale_range=HEAVY_SCALES)


#: scale bounds (m) of scene (b)
HEAVY_SCALES = (5e-4, 0.1)
#: house, frame count and seed of the walk that scene (c)'s map is built from (a development house)
HOUSE_SEED, HOUSE_FRAMES = 0, 40
_HOUSE_FORMAT = "splatsearch-bench-house-1"


def house_cache_path(seed: int = HOUSE_SEED, n_frames: int = HOUSE_FRAMES) -> str:
    """``$XDG_CACHE_HOME/splatsearch/bench/house<seed>_<n>f.npz`` (``~/.cache`` by default)."""
    import os

    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "splatsearch", "bench", f"house{seed}_{n_frames}f.npz")


def house_map(seed: int = HOUSE_SEED, n_frames: int = HOUSE_FRAMES, path: str | None = None,
              progress=None) -> dict:
    """The map scene (c) renders: ``{means, quats, scales, opacities, colors (float32), viewmats
    (F, 4, 4), K (3, 3) at 320x240}``, the active Gaussians of a :class:`~splatsearch.mapper.Mapper`
    (default config, 15 iterations) after ``n_frames`` frames of ``sim_trajectory(seed)``.

    Loaded from ``path``; by default from the fixture ``benchmarks/data/house<seed>_<n>f.npz`` of a
    source checkout, else from :func:`house_cache_path`. When missing it is built (1-6 s per frame
    on 2 cores) and written atomically there. ``progress(i, n)`` is called per mapped frame.
    """
    import io
    import os

    if path is None:
        # a source checkout ships the default map as a fixture (1.2 MB), so every run renders the same map
        fixture = os.path.join(os.path.dirname(__file__), "..", "benchmarks", "data", f"house{seed}_{n_frames}f.npz")
        path = fixture if os.path.exists(fixture) else house_cache_path(seed, n_frames)
    if os.path.exists(path):
        try:
            with np.load(path, allow_pickle=False) as z:
                if str(z["format"]) == _HOUSE_FORMAT:
                    return {k: z[k] for k in z.files if k != "format"}
        except (OSError, ValueError, KeyError):
            pass  # unreadable or stale: rebuild
    import jax

    from splatsearch.datasets import sim_trajectory
    from splatsearch.gaussians import render_args
    from splatsearch.io import atomic_write_bytes
    from splatsearch.mapper import Mapper

    frames, K, W, H, _ = sim_trajectory(seed, n_frames)
    m = Mapper(K, W, H)
    for i, f in enumerate(frames):
        m.update(f.rgb, f.depth, f.viewmat)
        if progress is not None:
            progress(i + 1, len(frames))
    n = m.map.n_active
    args = [np.asarray(a)[:n] for a in jax.device_get(render_args(m.map.params(), m.map.active, m.map.isotropic))]
    out = dict(zip(("means", "quats", "scales", "opacities", "colors"), (a.astype(np.float32) for a in args)))
    out["viewmats"] = np.stack([np.asarray(f.viewmat, np.float32) for f in frames])
    out["K"] = np.asarray(K, np.float32)
    buf = io.BytesIO()
    np.savez_compressed(buf, format=np.array(_HOUSE_FORMAT), **out)
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    atomic_write_bytes(path, buf.getvalue())
    return out


def house_scene(width: int = 320, height: int = 240, frame: int = HOUSE_FRAMES // 2, seed: int = HOUSE_SEED,
                n_frames: int = HOUSE_FRAMES) -> Scene:
    """Scene (c): the cached house map seen from pose ``frame`` of its walk; K is scaled from the
    walk's 320x240 intrinsics to ``width`` x ``height``."""
    d = house_map(seed, n_frames)
    K = d["K"].copy()
    K[0] *= width / 320.0
    K[1] *= height / 240.0
    f32 = lambda x: np.ascontiguousarray(x, np.float32)  # noqa: E731
    q = d["quats"] / np.maximum(np.linalg.norm(d["quats"], axis=1, keepdims=True), 1e-12)
    return Scene(f32(d["means"]), f32(q), f32(d["scales"]), f32(d["opacities"]), f32(d["colors"]),
                 f32(d["viewmats"][frame]), f32(K), width, height)


def random_scene(n: int = 10_000, width: int = 320, height: int = 240, seed: int = 0) -> Scene:
    """Scene (d): n Gaussians in a 4 m cube in front of a camera."""
    rng = np.random.default_rng(seed)
    means = rng.uniform(-2, 2, (n, 3)) + np.array([0, 0, 4.0])
    quats = rng.normal(size=(n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    scales = rng.uniform(0.005, 0.05, (n, 3))
    f32 = lambda x: np.ascontiguousarray(x, np.float32)  # noqa: E731
    return Scene(f32(means), f32(quats), f32(scales), f32(rng.uniform(0, 1, n)), f32(rng.uniform(0, 1, (n, 3))),
                 np.eye(4, dtype=np.float32), intrinsics_from_hfov(width, height, 79.0), width, height)


def scene_makers() -> dict:
    """``{name: make}`` with ``make()`` returning ``[(label, Scene), ...]`` for scenes (a)-(d)."""
    return {
        "profile": lambda: [("(a) profile 112k 648x420", profile_scene())],
        "heavy": lambda: [("(b) heavy 112k 648x420", heavy_scene())],
        "house": lambda: [(f"(c) house {w}x{h}", house_scene(w, h)) for w, h in ((320, 240), (640, 480))],
        "random10k": lambda: [("(d) random 10k 320x240", random_scene())],
    }


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


def time_call_cpu(fn, repeats: int = 5, warmup: int = 2,
                  cpu_clock: Callable[[], float] = time.process_time) -> tuple[float, float]:
    """(median wall seconds, median CPU seconds) of ``fn()``; CPU seconds by ``cpu_clock``: the
    process's, all threads (default), or ``time.thread_time`` for a single-threaded launch. On a
    machine shared with other jobs the CPU seconds are the steadier figure: CPU seconds / threads
    is about the wall time the call would take with its cores to itself."""
    for _ in range(warmup):
        fn()
    walls, cpus = [], []
    for _ in range(repeats):
        c0, t0 = cpu_clock(), time.perf_counter()
        fn()
        walls.append(time.perf_counter() - t0)
        cpus.append(cpu_clock() - c0)
    return float(np.median(walls)), float(np.median(cpus))


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
    fwd_cpu_s: float = float("nan")  # process CPU seconds (all threads) of one forward
    fwd_bwd_cpu_s: float = float("nan")

    @property
    def evals_per_s(self) -> float:
        return self.evals / self.fwd_s

    @property
    def peak_fraction(self) -> float:
        return self.evals_per_s / CPU_PEAK_EVALS_PER_S


def make_render_fns(scene: Scene, composite: str | None = None, threads: int | None = None):
    """Jitted ``forward(*params)`` and ``forward+backward(*params)`` on ``scene`` (RGB+D);
    ``composite`` and ``threads`` as for :func:`splatsearch.rasterize`."""
    import jax
    import jax.numpy as jnp

    from splatsearch.rasterization import rasterize

    W, H = scene.width, scene.height

    def fwd(m, q, s, o, c, vm, K):
        out = rasterize(m, q, s, o, c, vm, K, W, H, render_mode="RGB+D", composite=composite, threads=threads)
        return out.image, out.depth, out.alpha

    def loss(m, q, s, o, c, vm, K):
        img, dep, alp = fwd(m, q, s, o, c, vm, K)
        return jnp.mean(img) + 0.1 * jnp.mean(dep) + jnp.mean(alp)

    params = tuple(jnp.asarray(a) for a in scene.args[:7])
    return jax.jit(fwd), jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2, 3, 4, 5))), params


def run_benchmark(scene: Scene, name: str, repeats: int = 5, composite: str | None = None,
                  threads: int | None = None) -> BenchResult:
    """Time forward and forward+backward of ``scene`` (median of ``repeats`` after warm-up)."""
    import jax

    from splatsearch.rasterization import rasterize

    fwd, fwd_bwd, params = make_render_fns(scene, composite, threads)
    t_f, c_f = time_call_cpu(lambda: jax.block_until_ready(fwd(*params)), repeats)
    t_fb, c_fb = time_call_cpu(lambda: jax.block_until_ready(fwd_bwd(*params)), repeats)
    n_isect = int(rasterize(*params, scene.width, scene.height).meta["n_isect"])
    return BenchResult(name, scene.means.shape[0], scene.width, scene.height, n_isect,
                       count_gaussian_pixel_evaluations(scene), t_f, t_fb, c_f, c_fb)
