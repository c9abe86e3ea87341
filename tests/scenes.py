"""Small random test scenes covering the rasterizer's edge cases."""

from __future__ import annotations

import jax
import numpy as np

from splatsearch.bench import look_at  # noqa: F401  (re-exported for the tests)

#: The rasterizer runs its CUDA kernels (splatsearch.rasterization picks "cuda" on a GPU backend).
ON_CUDA = jax.default_backend() == "gpu"

W, H = 70, 50  # deliberately not multiples of the 16-px tile


def intrinsics(width: int = W, height: int = H, f: float = 60.0) -> np.ndarray:
    return np.array([[f, 0, width / 2 + 0.3], [0, f * 1.05, height / 2 - 0.2], [0, 0, 1]], np.float32)


def camera():
    return look_at([0.3, -3.0, 0.4], [0.0, 0.0, 0.0]), intrinsics()


def _params(rng, means, smin=0.02, smax=0.3):
    n = means.shape[0]
    quats = rng.normal(size=(n, 4))
    scales = np.exp(rng.uniform(np.log(smin), np.log(smax), (n, 3)))
    opac = rng.uniform(0.05, 0.99, n)
    colors = rng.uniform(0, 1, (n, 3))
    f = lambda a: np.asarray(a, np.float32)  # noqa: E731
    return f(means), f(quats), f(scales), f(opac), f(colors)


def random_scene(seed: int, n: int = 120):
    rng = np.random.default_rng(seed)
    means = rng.normal(0, 0.8, (n, 3))
    return _params(rng, means)


def scene(kind: str, seed: int = 0):
    """Named edge-case scenes, all seen by :func:`camera`."""
    rng = np.random.default_rng(seed)
    vm, K = camera()
    if kind == "random":
        return random_scene(seed)
    if kind == "empty":
        return tuple(np.zeros(s, np.float32) for s in [(0, 3), (0, 4), (0, 3), (0,), (0, 3)])
    if kind == "single":
        return _params(rng, np.array([[0.1, 0.0, 0.05]]), 0.1, 0.3)
    if kind == "straddle":
        # camera-space points that project exactly onto tile corners and edges
        Kinv = np.linalg.inv(K.astype(np.float64))
        pix = np.array([[16, 16], [32, 16], [16, 32], [48, 32], [32.0, 8], [64, 40]])
        z = rng.uniform(2.5, 3.5, len(pix))
        pc = (Kinv @ np.c_[pix, np.ones(len(pix))].T).T * z[:, None]
        inv = np.linalg.inv(vm.astype(np.float64))
        means = pc @ inv[:3, :3].T + inv[:3, 3]
        return _params(rng, means, 0.05, 0.2)
    if kind == "full_frame":
        m, q, s, o, c = _params(rng, rng.normal(0, 0.3, (20, 3)))
        s[0] = [3.0, 3.0, 3.0]
        m[0] = [0, 1.0, 0]
        o[0] = 0.9
        return m, q, s, o, c
    if kind == "subpixel":
        return _params(rng, rng.normal(0, 0.7, (80, 3)), 1e-4, 3e-3)
    if kind == "behind":
        inv = np.linalg.inv(vm.astype(np.float64))
        pc = np.c_[rng.uniform(-1, 1, (40, 2)), rng.uniform(-2.0, 3.0, 40)]
        means = pc @ inv[:3, :3].T + inv[:3, 3]
        return _params(rng, means, 0.05, 0.4)
    if kind == "near_plane":
        inv = np.linalg.inv(vm.astype(np.float64))
        pc = np.c_[rng.uniform(-0.05, 0.05, (30, 2)), rng.uniform(-0.05, 0.1, 30)]
        means = pc @ inv[:3, :3].T + inv[:3, 3]
        return _params(rng, means, 0.01, 0.08)
    raise KeyError(kind)


KINDS = ["random", "empty", "single", "straddle", "full_frame", "subpixel", "behind", "near_plane"]
