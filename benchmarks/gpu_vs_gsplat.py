"""On a CUDA GPU: splatsearch's Warp rasterizer vs gsplat, same scenes, one run.

    python benchmarks/gpu_vs_gsplat.py [--scenes profile,heavy,house,random10k] [--repeats 20]

Needs a CUDA GPU, JAX with CUDA (``pip install 'jax[cuda12]'``), PyTorch with CUDA and gsplat
(``pip install gsplat``); installed on the GPU machine only, never a dependency of the project.
Both render RGB+D of the scenes in :mod:`splatsearch.bench` (gsplat 1.5 classic rules, the ones
ours follows); the script prints per scene the tile intersections, forward and forward+backward
milliseconds of each (median of ``--repeats`` after warm-up, synchronised), their ratios, and the
largest image and alpha difference. Exit status 2 with a message when a requirement is missing.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))


def _fail(msg: str) -> None:
    print(f"gpu_vs_gsplat: {msg}", file=sys.stderr)
    sys.exit(2)


def check_requirements():
    """Import torch, gsplat, jax and warp and check that each sees a CUDA device."""
    try:
        import torch
    except ImportError:
        _fail("PyTorch is not installed (pip install torch); this script runs on a GPU machine only")
    if not torch.cuda.is_available():
        _fail("PyTorch sees no CUDA device; this comparison needs a GPU")
    try:
        import gsplat
    except ImportError:
        _fail("gsplat is not installed (pip install gsplat); it is installed on the GPU machine only")
    import jax

    if jax.default_backend() != "gpu":
        _fail(f"JAX runs on {jax.default_backend()!r}, not a GPU (pip install 'jax[cuda12]')")
    import warp as wp

    wp.config.quiet = True
    if not wp.is_cuda_available():
        _fail("Warp finds no CUDA device")
    return torch, gsplat


def _median_ms(fn, sync, repeats: int, warmup: int = 3) -> float:
    for _ in range(warmup):
        fn()
    sync()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        ts.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(ts))


def compare(scene, name: str, torch, gsplat, repeats: int) -> dict:
    import jax

    from splatsearch import bench

    fwd, fwd_bwd, params = bench.make_render_fns(scene)
    W, H = scene.width, scene.height

    def jsync():
        jax.block_until_ready(params)

    t_ours_f = _median_ms(lambda: jax.block_until_ready(fwd(*params)), jsync, repeats)
    t_ours_fb = _median_ms(lambda: jax.block_until_ready(fwd_bwd(*params)), jsync, repeats)
    img_o, dep_o, alp_o = (np.asarray(x) for x in fwd(*params))
    from splatsearch.rasterization import rasterize

    n_isect = int(rasterize(*params, W, H).meta["n_isect"])

    dev = torch.device("cuda")
    tp = [torch.tensor(np.asarray(a), device=dev) for a in scene.args[:7]]
    means, quats, scales, opac, colors, vm, K = tp

    def g_fwd(m, q, s, o, c):
        rc, ra, _ = gsplat.rasterization(m, q, s, o, c, vm[None], K[None], W, H, render_mode="RGB+D",
                                          near_plane=0.01, far_plane=1e10, eps2d=0.3, packed=False)
        return rc, ra

    leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors)]

    def g_fb():
        rc, ra = g_fwd(*leaves)
        loss = rc[..., :3].mean() + 0.1 * rc[..., 3:].mean() + ra.mean()
        loss.backward()
        return loss

    sync = torch.cuda.synchronize
    with torch.no_grad():
        t_g_f = _median_ms(lambda: g_fwd(means, quats, scales, opac, colors), sync, repeats)
        rc, ra = g_fwd(means, quats, scales, opac, colors)
    t_g_fb = _median_ms(g_fb, sync, repeats)
    rc = rc[0].cpu().numpy()
    ra = ra[0].cpu().numpy()
    return {"scene": name, "n": scene.means.shape[0], "res": f"{W}x{H}", "isect": n_isect,
            "ours_f": t_ours_f, "ours_fb": t_ours_fb, "gs_f": t_g_f, "gs_fb": t_g_fb,
            "d_img": float(np.abs(rc[..., :3] - img_o).max()), "d_alpha": float(np.abs(ra - alp_o).max()),
            "d_depth": float(np.abs(rc[..., 3:] - dep_o).max())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="profile,heavy,house,random10k",
                    help="comma-separated scene names from splatsearch.bench (default: all four)")
    ap.add_argument("--repeats", type=int, default=20, help="timed repetitions per pass after 3 warm-ups (default 20)")
    args = ap.parse_args()
    if args.repeats < 1:
        ap.error("--repeats must be >= 1")
    from splatsearch import bench

    makers = bench.scene_makers()
    unknown = [s for s in args.scenes.split(",") if s not in makers]
    if unknown:
        ap.error(f"unknown scenes {unknown}; choose from {sorted(makers)}")
    torch, gsplat = check_requirements()
    print(f"gsplat {getattr(gsplat, '__version__', '?')}, torch {torch.__version__}, "
          f"GPU {torch.cuda.get_device_name()}")
    print(f"{'scene':22s} {'isect':>10s} {'ours f':>9s} {'gsplat f':>9s} {'ratio':>6s} "
          f"{'ours fb':>9s} {'gsplat fb':>9s} {'ratio':>6s} {'max|dimg|':>9s} {'max|da|':>8s}")
    for name in args.scenes.split(","):
        for label, scene in makers[name]():
            r = compare(scene, label, torch, gsplat, args.repeats)
            print(f"{label:22s} {r['isect']:10,d} {r['ours_f']:8.2f}ms {r['gs_f']:8.2f}ms {r['gs_f'] / r['ours_f']:5.2f}x "
                  f"{r['ours_fb']:8.2f}ms {r['gs_fb']:8.2f}ms {r['gs_fb'] / r['ours_fb']:5.2f}x "
                  f"{r['d_img']:9.1e} {r['d_alpha']:8.1e}", flush=True)
    print("ratio > 1: ours is faster. Times are medians after warm-up, synchronised on both sides.")


if __name__ == "__main__":
    main()
