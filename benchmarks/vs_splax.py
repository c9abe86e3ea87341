"""splatsearch's rasterizer vs splax 0.2.3 on the CPU, scenes (a) profile and (b) heavy, one run.

    python benchmarks/vs_splax.py [--scenes profile,heavy] [--repeats 5] [--rounds 2]
                                  [--splax-venv /tmp/splax-0.2.3]

splax is never a dependency of the project: the script creates a throwaway virtual environment
outside the repository (``python -m venv DIR && DIR/bin/pip install splax==0.2.3``) the first
time, and times splax there in a subprocess that reads the same scene from a temporary .npz.
The two sides alternate (ours, splax, ours, ... for ``--rounds`` rounds) so that a change in the
machine's load hits both; the table gives the median over rounds of each round's median, and the
ratios splax / ours. Both jit the forward (RGB + depth) and forward + backward (value_and_grad of
mean image + 0.1 mean depth + mean alpha w.r.t. every Gaussian parameter) and block on the result.
The splax image is compared with ours; a row whose images differ by more than ``IMAGE_TOL``
is marked INVALID. splax's kernels are cooperative tile kernels (256 threads per 16x16 tile
sharing batches of Gaussians); on the CPU they need Warp >= 1.19 with
``wp.config.enable_cpu_blocks = True`` (the worker sets it): Warp's CPU default runs one thread
per block, which renders one pixel per tile from uninitialised batches (near-black images and
crashes in the depth backward). Warp 1.14, the oldest splax 0.2.3 accepts, registers its JAX FFI
targets for CUDA only ("No FFI handler registered ... on a platform Host"); 1.18 and 1.19 register
CPU targets and have the same ``enable_cpu_blocks`` switch, off by default. Not part of the test
suite (a run takes minutes).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

SH_C0 = 0.28209479177387814
#: largest image / alpha difference at which the two renders count as the same picture (splax
#: differs in small rules: its own radius cut, no 1e-4 transmittance stop on the last Gaussian)
IMAGE_TOL = 0.05


def _time(fn, repeats: int, warmup: int = 2) -> float:
    for _ in range(warmup):
        fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def splax_worker(npz: str, repeats: int, render_depth: bool = True, warmup: int = 2,
                 backward: bool = True) -> None:
    """Runs inside the splax venv: time splax.render on the scene, print JSON seconds."""
    import jax
    import jax.numpy as jnp
    import warp as wp

    # splax 0.2.3 asks for Warp graph capture in its projection FFI calls, which Warp 1.19 refuses on
    # the CPU ("JaxCallableGraphMode.WARP is not supported for JAX CPU FFI calls"); graph capture
    # is a CUDA launch optimisation, so on the CPU the same kernels run with plain launches.
    if jax.default_backend() == "cpu":
        # splax's kernels are cooperative tile kernels (launch_tiled, block_dim 256, shared-memory
        # batches of Gaussians loaded by the block's threads). Warp's CPU default resolves every
        # block_dim to 1 (``wp.config.enable_cpu_blocks = False``): then only thread 0 of each
        # 16x16 tile runs, so only one pixel per tile is rendered and the shared batches hold one
        # loaded Gaussian and uninitialised records (the near-black images and the crashes of the
        # depth backward seen before). Warp >= 1.19 runs CPU blocks of 2-1024 threads as
        # cooperative fibers when asked to.
        wp.config.enable_cpu_blocks = True
        _jax_callable = wp.jax_callable

        def _cpu_jax_callable(*a, **kw):
            kw["graph_mode"] = wp.JaxCallableGraphMode.NONE
            return _jax_callable(*a, **kw)

        wp.jax_callable = _cpu_jax_callable
    import splax

    d = np.load(npz)
    H, W = int(d["height"]), int(d["width"])
    K = d["K"]
    o = np.clip(d["opacities"], 1e-6, 1 - 1e-6)
    args = (jnp.asarray(d["means"]), jnp.asarray(np.log(np.maximum(d["scales"], 1e-12))), jnp.asarray(d["quats"]),
            jnp.asarray(((d["colors"] - 0.5) / SH_C0)[:, None, :]), jnp.asarray(np.log(o / (1 - o))))
    vm = jnp.asarray(d["viewmat"])
    kw = dict(viewmat=vm, background=jnp.zeros(3), img_shape=(H, W), f=(float(K[0, 0]), float(K[1, 1])),
              c=(float(K[0, 2]), float(K[1, 2])), render_depth=render_depth)

    def fwd(*a):
        return splax.render(*a, **kw)

    def loss(*a):
        img, alpha = fwd(*a)
        return jnp.mean(img[..., :3]) + (0.1 * jnp.mean(img[..., 3]) if render_depth else 0.0) + jnp.mean(alpha)

    f = jax.jit(fwd)
    fb = jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2, 3, 4)))
    t_f = _time(lambda: jax.block_until_ready(f(*args)), repeats, warmup)
    t_fb = _time(lambda: jax.block_until_ready(fb(*args)), repeats, warmup) if backward else float("nan")
    img, alpha = f(*args)
    np.save(npz + ".splax.npy", np.concatenate([np.asarray(img)[..., :3], np.asarray(alpha)[..., None]], -1))
    print(json.dumps({"fwd": t_f, "fwd_bwd": t_fb}))


def ensure_splax_venv(path: str) -> str:
    py = os.path.join(path, "bin", "python")
    ok = os.path.exists(py) and subprocess.run([py, "-c", "import splax; assert splax.__version__ == '0.2.3'"],
                                               capture_output=True).returncode == 0
    if not ok:
        print(f"creating the throwaway venv {path} with splax==0.2.3 ...", flush=True)
        subprocess.run([sys.executable, "-m", "venv", path], check=True)
        subprocess.run([py, "-m", "pip", "install", "-q", "splax==0.2.3"], check=True)
    return py


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="profile,heavy", help="comma-separated: profile, heavy (default both)")
    ap.add_argument("--repeats", type=int, default=5, help="timed calls per pass and round (default 5)")
    ap.add_argument("--rounds", type=int, default=2, help="alternating rounds ours/splax (default 2)")
    ap.add_argument("--warmup", type=int, default=2,
                    help="untimed calls before each timed pass, the first compiles (default 2; splax's CPU "
                         "backward takes over a minute per call on (a))")
    ap.add_argument("--splax-venv", default=os.path.join(tempfile.gettempdir(), "splax-0.2.3-venv"),
                    help="throwaway venv holding splax 0.2.3, created if missing (default: $TMPDIR/splax-0.2.3-venv)")
    ap.add_argument("--forward-only", action="store_true",
                    help="time the forward only (splax's CPU backward is slow; the f+b columns read nan)")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--worker-depth", type=int, default=1, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        splax_worker(args.worker, args.repeats, bool(args.worker_depth), args.warmup, not args.forward_only)
        return
    if args.repeats < 1 or args.rounds < 1 or args.warmup < 1:
        ap.error("--repeats, --rounds and --warmup must be >= 1")
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
    import jax

    from splatsearch import bench

    makers = {"profile": bench.profile_scene, "heavy": bench.heavy_scene}
    names = args.scenes.split(",")
    bad = [n for n in names if n not in makers]
    if bad:
        ap.error(f"unknown scenes {bad}; choose from {sorted(makers)}")
    py = ensure_splax_venv(args.splax_venv)
    load = os.getloadavg()
    print(f"load average before: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}", flush=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            scene = makers[name]()
            npz = os.path.join(tmp, f"{name}.npz")
            np.savez(npz, means=scene.means, quats=scene.quats, scales=scene.scales, opacities=scene.opacities,
                     colors=scene.colors, viewmat=scene.viewmat, K=scene.K, width=scene.width, height=scene.height)
            fwd, fwd_bwd, params = bench.make_render_fns(scene)
            ours_f, ours_fb, sp_f, sp_fb = [], [], [], []
            for _ in range(args.rounds):
                ours_f.append(bench.time_call(lambda: jax.block_until_ready(fwd(*params)), args.repeats,
                                              args.warmup)[0])
                ours_fb.append(float("nan") if args.forward_only else
                               bench.time_call(lambda: jax.block_until_ready(fwd_bwd(*params)), args.repeats,
                                               args.warmup)[0])
                for _attempt in range(3):  # a crashed worker is retried (it crashed without enable_cpu_blocks)
                    out = subprocess.run([py, os.path.abspath(__file__), "--worker", npz, "--repeats", str(args.repeats),
                                          "--warmup", str(args.warmup)]
                                         + (["--forward-only"] if args.forward_only else []),
                                         capture_output=True, text=True, env={**os.environ, "JAX_PLATFORMS": "cpu"})
                    if out.returncode >= 0:
                        break
                    print(f"splax worker died with signal {-out.returncode}; retrying", flush=True)
                if out.returncode != 0:
                    sys.exit(f"splax worker failed (exit status {out.returncode}):\n{out.stderr[-3000:]}")
                r = json.loads(out.stdout.strip().splitlines()[-1])
                sp_f.append(r["fwd"])
                sp_fb.append(r["fwd_bwd"])
            from splatsearch.rasterization import rasterize

            ours = rasterize(*params, scene.width, scene.height)
            n_isect = int(ours.meta["n_isect"])
            theirs = np.load(npz + ".splax.npy")
            d_img = float(np.abs(theirs[..., :3] - np.asarray(ours.image)).max())
            d_alpha = float(np.abs(theirs[..., 3:] - np.asarray(ours.alpha)).max())
            rows.append((name, n_isect, np.median(ours_f), np.median(sp_f), np.median(ours_fb), np.median(sp_fb),
                         ours_f, sp_f, ours_fb, sp_fb, d_img, d_alpha))
    load = os.getloadavg()
    print(f"load average after: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    print(f"{'scene':8s} {'isect':>9s} {'ours fwd':>9s} {'splax fwd':>10s} {'ratio':>6s} "
          f"{'ours f+b':>9s} {'splax f+b':>10s} {'ratio':>6s}")
    for name, ni, of, sf, ofb, sfb, *_, d_img, d_alpha in rows:
        ok = d_img <= IMAGE_TOL and d_alpha <= IMAGE_TOL
        print(f"{name:8s} {ni:9,d} {1e3 * of:7.1f}ms {1e3 * sf:8.1f}ms {sf / of:5.2f}x "
              f"{1e3 * ofb:7.1f}ms {1e3 * sfb:8.1f}ms {sfb / ofb:5.2f}x  max|dimg| {d_img:.3f} max|dalpha| {d_alpha:.3f}"
              + ("" if ok else "  INVALID: splax rendered another image; its times do not count"))
    for name, _, _, _, _, _, of, sf, ofb, sfb, *_ in rows:
        print(f"{name} per round (ms): ours fwd {[round(1e3 * x, 1) for x in of]}, splax fwd "
              f"{[round(1e3 * x, 1) for x in sf]}, ours f+b {[round(1e3 * x, 1) for x in ofb]}, "
              f"splax f+b {[round(1e3 * x, 1) for x in sfb]}")


if __name__ == "__main__":
    main()
