"""Old vs new tile compositing kernels on the benchmark scenes, alternating in one process.

    python benchmarks/composite_ab.py OLD_KERNELS_DIR [--scenes heavy,profile] [--rounds 3] [--repeats 3]

``OLD_KERNELS_DIR`` is a copy of an earlier ``kernels/`` directory (e.g. ``git show`` of a commit
extracted with ``git archive <commit> kernels | tar -x -C /tmp/old``, then ``/tmp/old/kernels``),
imported as a package of its own. Both sides composite the same projection and binning (this
checkout's) with one thread per launch; the script times each forward and backward compositing
launch (wall and thread CPU seconds, median of ``--repeats`` per round), alternating old and new
for ``--rounds`` rounds, and prints the machine load, the medians and the new/old speed-ups, plus
the largest image / gradient difference between the two. Not part of the test suite.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time

import numpy as np


def _load_old(path: str):
    spec = importlib.util.spec_from_file_location("old_kernels", os.path.join(path, "__init__.py"),
                                                  submodule_search_locations=[path])
    mod = importlib.util.module_from_spec(spec)
    sys.modules["old_kernels"] = mod
    spec.loader.exec_module(mod)
    return importlib.import_module("old_kernels.composite")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("old", help="directory of the old kernels/ package")
    ap.add_argument("--scenes", default="heavy,profile", help="comma-separated scene names of `splatsearch bench`")
    ap.add_argument("--rounds", type=int, default=3, help="alternating rounds (default 3)")
    ap.add_argument("--repeats", type=int, default=3, help="timed launches per side and round (default 3)")
    args = ap.parse_args()
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
    import warp as wp

    wp.config.quiet = True
    from splatsearch import bench
    from splatsearch.kernels import composite as new_c
    from splatsearch.kernels import pipeline as pl

    old_c = _load_old(os.path.abspath(args.old))
    dev = "cpu"
    for name in args.scenes.split(","):
        for label, sc in bench.scene_makers()[name]():
            n, W, H, C = sc.means.shape[0], sc.width, sc.height, 3
            arr = lambda x, dt: wp.array(x, dtype=dt, device=dev)  # noqa: E731
            means2d, conics = wp.empty(n, dtype=wp.vec2), wp.empty(n, dtype=wp.vec3)
            depths, radii = wp.empty(n, dtype=wp.float32), wp.empty(n, dtype=wp.vec2i)
            opac, colors = arr(sc.opacities, wp.float32), arr(sc.colors, wp.vec3)
            pl.project(arr(sc.means, wp.vec3), arr(sc.quats, wp.vec4), arr(sc.scales, wp.vec3), opac,
                       arr(sc.viewmat[None], wp.mat44), arr(sc.K[None], wp.mat33), W, H, 0.01, 1e10, 0.3,
                       means2d, conics, depths, radii, threads=1)
            ws = pl.Workspace(dev)
            ranges, ids, n_isect = pl.bin_gaussians(ws, means2d, conics, opac, depths, radii, W, H, threads=1)
            tx, ty = pl.grid_dims(W, H)
            nt, hw = tx * ty, W * H
            colf = wp.array(ptr=colors.ptr, shape=(n * C,), dtype=wp.float32, device=dev, copy=False)
            rng = np.random.default_rng(0)
            v_color = arr(rng.normal(size=(hw, 3)).astype(np.float32), wp.vec3)
            v_depth = arr(rng.normal(size=hw).astype(np.float32), wp.float32)
            v_alpha = arr(rng.normal(size=hw).astype(np.float32), wp.float32)

            def outs():
                return (wp.zeros(hw, dtype=wp.vec3), wp.zeros(hw, dtype=wp.float32), wp.zeros(hw, dtype=wp.float32),
                        wp.zeros(hw, dtype=wp.int32))

            def grads():
                return (wp.zeros(n, dtype=wp.vec2), wp.zeros(n, dtype=wp.vec3), wp.zeros(n, dtype=wp.float32),
                        wp.zeros(n, dtype=wp.vec3), wp.zeros(n, dtype=wp.float32))

            o_out, n_out, o_g, n_g = outs(), outs(), grads(), grads()
            ofwd, obwd = old_c.composite_tile_kernels(C)
            nfwd, nbwd = new_c.composite_tile_kernels(C)
            o_scr = (wp.empty(hw, dtype=wp.int32), wp.empty(nt * 16, dtype=wp.vec2i))
            o_bscr = (wp.empty(hw, dtype=wp.float32), wp.empty(hw, dtype=wp.vec3), wp.empty(hw, dtype=wp.float32),
                      wp.empty(nt * 16, dtype=wp.int32))
            n_scr = (wp.empty(nt * 256), wp.empty(nt * 256), wp.empty(nt * 256, dtype=wp.int32),
                     wp.empty(nt * 256 * C), wp.empty(nt * 16, dtype=wp.vec2i))
            n_bscr = (wp.empty(nt * 256 * new_c.bwd_scratch_fields(C)), wp.empty(nt * 256, dtype=wp.int32),
                      wp.empty(nt * 16 * (7 + C)), wp.empty(nt * (7 + C)), wp.empty(nt * 16, dtype=wp.int32))
            geo = [ranges, ids, means2d, conics, opac]

            def simd_style(k) -> bool:  # per-tile scratch signature (flat colours or records)
                return any(arg.label in ("colf", "rec") for arg in k.adj.args)

            def launch_f(k, out):
                if any(arg.label == "rec" for arg in k.adj.args):  # packed records, built inside the timing
                    rec = pl.splat_records(ws, means2d, conics, opac, depths, colors, radii, threads=1)
                    wp.launch(k, dim=nt, inputs=[ranges, ids, rec, W, H, tx, 0, *n_scr], outputs=list(out))
                elif simd_style(k):
                    wp.launch(k, dim=nt, inputs=geo + [colf, depths, W, H, tx, 0, *n_scr], outputs=list(out))
                else:
                    wp.launch(k, dim=nt, inputs=geo + [colors, depths, W, H, 16, tx, 0, *o_scr], outputs=list(out))

            def launch_b(k, out, g):
                for a in g:
                    a.zero_()
                if any(arg.label == "rec" for arg in k.adj.args):  # packed records, built inside the timing
                    rec = pl.splat_records(ws, means2d, conics, opac, depths, colors, radii, threads=1)
                    wp.launch(k, dim=nt, inputs=[ranges, ids, rec, W, H, tx, 0, out[2], out[3], v_color, v_depth,
                                                 v_alpha, *n_bscr], outputs=list(g))
                elif simd_style(k):
                    wp.launch(k, dim=nt, inputs=geo + [colf, depths, W, H, tx, 0, out[2], out[3], v_color, v_depth,
                                                       v_alpha, *n_bscr], outputs=list(g))
                else:
                    wp.launch(k, dim=nt, inputs=geo + [colors, depths, W, H, 16, tx, 0, out[2], out[3], v_color,
                                                       v_depth, v_alpha, *o_bscr], outputs=list(g))

            def old_f():
                launch_f(ofwd, o_out)

            def new_f():
                launch_f(nfwd, n_out)

            def old_b():
                launch_b(obwd, o_out, o_g)

            def new_b():
                launch_b(nbwd, n_out, n_g)

            for f in (old_f, new_f, old_b, new_b):
                f()
            res = {k: [] for k in ("old_f", "new_f", "old_b", "new_b")}
            load0 = os.getloadavg()[0]
            for _ in range(args.rounds):
                for key, f in (("old_f", old_f), ("new_f", new_f), ("old_b", old_b), ("new_b", new_b)):
                    res[key].append(bench.time_call_cpu(f, args.repeats, warmup=0, cpu_clock=time.thread_time))
            load1 = os.getloadavg()[0]
            d_img = max(float(np.abs(a.numpy() - b.numpy()).max()) for a, b in zip(o_out[:3], n_out[:3]))
            d_last = int((o_out[3].numpy() != n_out[3].numpy()).sum())
            d_grad = max(float(np.abs(a.numpy() - b.numpy()).max() / max(1e-30, np.abs(a.numpy()).max()))
                         for a, b in zip(o_g, n_g))
            med = {k: (float(np.median([w for w, _ in v])), float(np.median([c for _, c in v]))) for k, v in res.items()}
            print(f"{label}: isect {n_isect:,}, load {load0:.1f} -> {load1:.1f}, {args.rounds} rounds x {args.repeats}")
            for part in ("f", "b"):
                o, nw = med[f"old_{part}"], med[f"new_{part}"]
                print(f"  {'forward ' if part == 'f' else 'backward'}: old {1e3 * o[0]:7.1f} ms wall {1e3 * o[1]:7.1f} ms cpu"
                      f" | new {1e3 * nw[0]:7.1f} ms wall {1e3 * nw[1]:7.1f} ms cpu | speed-up wall {o[0] / nw[0]:.2f}x"
                      f" cpu {o[1] / nw[1]:.2f}x")
            print(f"  per round cpu ms: " + ", ".join(f"{k} {[round(1e3 * c, 1) for _, c in v]}" for k, v in res.items()))
            print(f"  max |image diff| {d_img:.2e}, pixels with another last index {d_last}, "
                  f"max relative gradient diff {d_grad:.2e}", flush=True)


if __name__ == "__main__":
    main()
