"""Side by side: the Warp tile rasterizer vs the dense pure-JAX reference, in one run.

    python benchmarks/compare_dense.py [--n 4000] [--width 160] [--height 120] [--repeats 3]

Both render the same random scene (RGB+D) in float32 under jax.jit, forward and forward +
backward; the script prints both times, their ratio, and the largest image difference.
"""

from __future__ import annotations

import argparse
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tests"))
import reference  # noqa: E402

from splatsearch import bench  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=4000)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    scene = bench.random_scene(args.n, args.width, args.height)
    W, H = scene.width, scene.height
    fwd, fwd_bwd, params = bench.make_render_fns(scene)

    def dense_fwd(m, q, s, o, c, vm, K):
        color, depth, alpha, _ = reference.rasterize_dense(m, q, s, o, c, vm, K, W, H)
        return color, depth, alpha

    def dense_loss(m, q, s, o, c, vm, K):
        img, dep, alp = dense_fwd(m, q, s, o, c, vm, K)
        return jnp.mean(img) + 0.1 * jnp.mean(dep) + jnp.mean(alp)

    dfwd = jax.jit(dense_fwd)
    dfb = jax.jit(jax.value_and_grad(dense_loss, argnums=(0, 1, 2, 3, 4, 5)))
    rows = []
    for label, ours, dense in (("forward", fwd, dfwd), ("forward+backward", fwd_bwd, dfb)):
        t_o, _ = bench.time_call(lambda: jax.block_until_ready(ours(*params)), args.repeats)
        t_d, _ = bench.time_call(lambda: jax.block_until_ready(dense(*params)), args.repeats, warmup=1)
        rows.append((label, t_o, t_d))
    diff = np.abs(np.asarray(fwd(*params)[0]) - np.asarray(dfwd(*params)[0])).max()
    print(f"scene: {args.n} Gaussians at {W}x{H}, RGB+D, float32, CPU")
    print(f"{'pass':18s} {'warp tiles':>12s} {'dense JAX':>12s} {'speed-up':>9s}")
    for label, t_o, t_d in rows:
        print(f"{label:18s} {1e3 * t_o:10.1f}ms {1e3 * t_d:10.1f}ms {t_d / t_o:8.1f}x")
    print(f"max |image difference| = {diff:.2e}")


if __name__ == "__main__":
    main()
