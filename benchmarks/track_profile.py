"""Where a tracking step's CPU time goes: per-stage thread CPU of one rasterizer forward + backward.

    SPLATSEARCH_THREADS=1 python benchmarks/track_profile.py [--size 320x240] [--steps 20]

Maps frames 0-19 of dev house 0 (320x240, the SIM settings of ``slam_eval.py``) with
ground-truth poses, takes the Gaussians visible from frame 21 as the tracker does (padded to a
power of two), and times a jitted forward, and a value_and_grad of the tracker's loss (masked
depth + 0.5 colour L1) with respect to an se(3) increment with the full ("all") and the
pose-only ("viewmat") backward. Each pipeline stage is wrapped to add up its thread CPU time,
so run it with one thread (``SPLATSEARCH_THREADS=1``): then every launch runs on the calling
thread and the stages sum to the Warp share of the step; the rest of the process CPU is JAX and
the FFI calls. ``--size`` renders smaller images (intrinsics scaled). Not part of the test suite.
"""

from __future__ import annotations

import argparse
import collections
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="320x240", help="image size WxH, a divisor of 320x240 (default 320x240)")
    ap.add_argument("--steps", type=int, default=20, help="timed calls per variant (default 20)")
    a = ap.parse_args(argv)
    try:
        W, H = (int(v) for v in a.size.lower().split("x"))
    except ValueError:
        ap.error(f"--size must look like 320x240, got {a.size!r}")
    if W <= 0 or 320 % W or H * 320 != W * 240 or a.steps < 1:
        ap.error("--size must be 320x240 divided by an integer, and --steps >= 1")
    import cv2
    import jax
    import jax.numpy as jnp

    sys.path.insert(0, HERE)
    from slam_eval import SIM

    from splatsearch import datasets
    from splatsearch.gaussians import render_args
    from splatsearch.kernels import pipeline as pl
    from splatsearch.mapper import Mapper, MapperConfig, _gather_rows
    from splatsearch.rasterization import rasterize
    from splatsearch.slam import perturb_viewmat, visible_rows

    seq = datasets.sim_walk(0, 22, 320, 240)
    m = Mapper(seq.K, 320, 240, MapperConfig(**SIM))
    for f in seq.frames[:20]:
        m.update(f.rgb, f.depth, f.viewmat)
    f = seq.frames[21]
    s = 320 // W
    K = np.asarray(seq.K, np.float32).copy()
    K[:2] /= s
    rgb = jnp.asarray(cv2.resize(f.rgb, (W, H), interpolation=cv2.INTER_AREA))
    depth = jnp.asarray(f.depth[s // 2::s, s // 2::s][:H, :W])
    vm0 = jnp.asarray(f.viewmat)
    rows = visible_rows(m.map, f.viewmat, K, W, H, 0.25)
    params, active, _, _ = _gather_rows(m.map, None, rows)
    margs = render_args(params, active, m.map.isotropic)
    Kj = jnp.asarray(K)
    print(f"{W}x{H}: {len(rows)} visible Gaussians, padded to {margs[0].shape[0]}; "
          f"threads {os.environ.get('SPLATSEARCH_THREADS', 'default')}, load {os.getloadavg()[0]:.2f}")

    def render(margs, xi, diff="all"):
        return rasterize(*margs, perturb_viewmat(vm0, xi), Kj, W, H, render_mode="RGB+D", validate=False,
                         differentiable=diff)

    def step(diff):
        def loss(margs, xi):
            out = render(margs, xi, diff)
            mk = jax.lax.stop_gradient(((out.alpha[..., 0] > 0.99) & (depth > 0)).astype(jnp.float32))
            return (jnp.sum(jnp.abs(out.depth[..., 0] - depth) * mk)
                    + 0.5 * jnp.sum(jnp.abs(out.image - rgb).sum(-1) * mk)) / mk.sum()
        vg = jax.jit(jax.value_and_grad(loss, argnums=1))
        return lambda: vg(margs, xi)[1].block_until_ready()

    xi = jnp.full((6,), 1e-3, jnp.float32)
    fwd = jax.jit(lambda margs, xi: render(margs, xi).depth.sum())
    calls = {"forward": lambda: fwd(margs, xi).block_until_ready(), "all": step("all"), "viewmat": step("viewmat")}
    for c in calls.values():
        c()
    T = collections.defaultdict(float)

    def timed(fn, name):
        def wrap(*args, **kw):
            t = time.thread_time()
            try:
                return fn(*args, **kw)
            finally:
                T[name] += time.thread_time() - t
        return wrap

    for name in ("rasterize_forward", "rasterize_backward", "rasterize_backward_pose", "bin_gaussians",
                 "splat_records", "project"):
        setattr(pl, name, timed(getattr(pl, name), name))
    run_bands = pl.run_bands
    pl.run_bands = lambda bands, n, fn, kernel=None, device=None: timed(run_bands, "  launch " + (
        kernel.key.split("__")[-1] if kernel is not None else "?"))(bands, n, fn, kernel, device)
    for name, c in calls.items():
        T.clear()
        c0 = time.process_time()
        for _ in range(a.steps):
            c()
        tot = 1e3 * (time.process_time() - c0) / a.steps
        warp = 1e3 * sum(v for k, v in T.items() if k.startswith("rasterize")) / a.steps
        print(f"{name}: process CPU {tot:.1f} ms per call; rasterizer stages {warp:.1f}; JAX, FFI, rest {tot - warp:.1f}")
        for k, v in sorted(T.items(), key=lambda kv: -kv[1]):
            print(f"   {k:40s} {1e3 * v / a.steps:.2f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
