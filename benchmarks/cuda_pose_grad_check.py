"""Check the pose-only backward (``differentiable="viewmat"``) on a device and time a tracking step.

    python benchmarks/cuda_pose_grad_check.py --device cuda     # on a GPU machine (default)
    python benchmarks/cuda_pose_grad_check.py --device cpu      # the same checks on the CPU

1. Small scenes (tests/scenes.py, 70x50): the pose-only viewmat gradient against the full
   backward's and against jax.grad of the dense float64 reference (tests/reference.py), for both
   compositing kernels.
2. A tracking-sized scene (``--gaussians`` random Gaussians, 320x240, a loss mask over 30 % of
   the pixels): pose-only against full backward.
3. Timing: one tracking step (jitted value_and_grad of an L1 colour + depth loss with respect
   to an se(3) increment), full vs pose-only backward, median of ``--repeats`` after warm-up.

Prints the max abs / relative differences and exits 1 on a mismatch (relative difference above
``--tol`` against the full backward, 1e-3 against the reference). Includes the Warp/XLA
compiles: about 27 s on an H200 with both kernels (``--composites pixel`` leaves out the tile
kernels' compiles).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", choices=["cuda", "cpu"], default="cuda", help="where to run (default cuda)")
    ap.add_argument("--gaussians", type=int, default=20000, help="Gaussians of the tracking-sized scene")
    ap.add_argument("--repeats", type=int, default=10, help="timed tracking steps per backward (default 10)")
    ap.add_argument("--tol", type=float, default=1e-4, help="relative tolerance against the full backward")
    ap.add_argument("--composites", default="pixel,tile",
                    help="compositing kernels of the small-scene checks (default pixel,tile; pixel is the CUDA default)")
    a = ap.parse_args(argv)
    if a.gaussians < 1 or a.repeats < 1 or not a.tol > 0:
        ap.error("--gaussians and --repeats must be >= 1 and --tol > 0")
    composites = a.composites.split(",")
    if not composites or any(c not in ("pixel", "tile") for c in composites):
        ap.error(f"--composites takes a comma-separated subset of pixel,tile, got {a.composites!r}")
    if a.device == "cpu":
        os.environ.setdefault("JAX_PLATFORMS", "cpu")
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    sys.path.insert(0, os.path.join(HERE, "..", "tests"))
    import reference
    import scenes

    import splatsearch
    from splatsearch.slam import perturb_viewmat

    try:
        dev = jax.devices("gpu" if a.device == "cuda" else "cpu")[0]
    except RuntimeError as e:
        print(f"cuda_pose_grad_check: no {a.device} device here ({e})", file=sys.stderr)
        return 2
    print(f"device: {dev}")
    ok = True

    def rel(x, y):
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        d = np.abs(x - y).max()
        return d, d / max(np.abs(y).max(), 1e-30)

    with jax.default_device(dev):
        W, H = scenes.W, scenes.H
        vm, K = scenes.camera()
        for composite in composites:
            for kind, seed in (("random", 0), ("random", 1), ("straddle", 0), ("full_frame", 0)):
                params = scenes.scene(kind, seed)
                rng = np.random.default_rng(seed)
                mask = rng.uniform(size=(H, W, 1)) < 0.6
                wc = jnp.asarray(rng.uniform(-1, 1, (H, W, 3)) * mask, jnp.float32)
                wd = jnp.asarray(rng.uniform(-1, 1, (H, W, 1)) * 0.3 * mask, jnp.float32)

                def ours(v, diff):
                    out = splatsearch.rasterize(*params, v, K, W, H, composite=composite, differentiable=diff)
                    return jnp.sum(out.image * wc) + jnp.sum(out.depth * wd)

                def ref(v):
                    args = [jnp.asarray(x, jnp.float64) for x in params]
                    color, depth, _, _ = reference.rasterize_dense(*args, v, jnp.asarray(K, jnp.float64), W, H)
                    return jnp.sum(color * wc) + jnp.sum(depth * wd)

                g_pose = jax.grad(ours)(jnp.asarray(vm), "viewmat")
                g_all = jax.grad(ours)(jnp.asarray(vm), "all")
                g_ref = jax.jit(jax.grad(ref))(jnp.asarray(vm, jnp.float64))
                d1, r1 = rel(g_pose, g_all)
                d2, r2 = rel(g_pose, g_ref)
                good = r1 <= a.tol and r2 <= 1e-3 and np.all(np.isfinite(np.asarray(g_pose)))
                ok &= bool(good)
                print(f"{composite:5s} {kind}/{seed}: pose vs full max abs {d1:.3g} rel {r1:.3g}; "
                      f"vs float64 reference max abs {d2:.3g} rel {r2:.3g}  {'ok' if good else 'MISMATCH'}")

        W, H = 320, 240
        K = scenes.intrinsics(W, H, 260.0)
        vm = scenes.look_at([0.2, -3.5, 0.3], [0.0, 0.0, 0.0])
        params = [jnp.asarray(x) for x in scenes.random_scene(11, a.gaussians)]
        params[2] = params[2] * 0.4  # smaller Gaussians: a denser, map-like scene
        rng = np.random.default_rng(5)
        mask = jnp.asarray(rng.uniform(size=(H, W)) < 0.7, jnp.float32)
        rgb = jnp.asarray(rng.uniform(0, 1, (H, W, 3)), jnp.float32)
        depth = jnp.asarray(rng.uniform(2, 4, (H, W)), jnp.float32)
        vmj = jnp.asarray(vm)

        def step_loss(xi, diff):
            out = splatsearch.rasterize(*params, perturb_viewmat(vmj, xi), K, W, H, render_mode="RGB+D",
                                        validate=False, differentiable=diff)
            return (jnp.sum(jnp.abs(out.depth[..., 0] - depth) * mask)
                    + 0.5 * jnp.sum(jnp.abs(out.image - rgb).sum(-1) * mask)) / mask.sum()

        xi = jnp.full((6,), 1e-3, jnp.float32)
        steps = {d: jax.jit(jax.value_and_grad(lambda x, d=d: step_loss(x, d))) for d in ("all", "viewmat")}
        grads = {d: np.asarray(f(xi)[1]) for d, f in steps.items()}
        d3, r3 = rel(grads["viewmat"], grads["all"])
        good = r3 <= a.tol and np.all(np.isfinite(grads["viewmat"]))
        ok &= bool(good)
        print(f"tracking scene {a.gaussians} Gaussians {W}x{H}: se(3) gradient pose vs full max abs {d3:.3g} "
              f"rel {r3:.3g}  {'ok' if good else 'MISMATCH'}")
        times = {d: [] for d in steps}
        for _ in range(a.repeats):
            for d, f in steps.items():
                t0 = time.perf_counter()
                jax.block_until_ready(f(xi))
                times[d].append(time.perf_counter() - t0)
        t_all, t_pose = np.median(times["all"]), np.median(times["viewmat"])
        print(f"tracking step (forward + backward), median of {a.repeats}: full {1e3 * t_all:.2f} ms, "
              f"pose-only {1e3 * t_pose:.2f} ms ({t_all / t_pose:.2f}x)")
    print("OK" if ok else "FAILED")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
