"""Quiet-machine wall time of the rasterizer, estimated on a busy machine from thread CPU time.

    python benchmarks/critical_path.py [--scenes heavy,profile] [--repeats 5]

On a machine shared with other jobs the wall time of a 2-thread call is inflated by waiting for a
core, and process CPU time mixes the workers. This script times the jitted RGB+D forward and
forward + backward of `splatsearch bench`'s scenes and sums the CPU time on the critical path:
the calling thread's CPU outside the split launches, plus for every split launch
(:func:`splatsearch.kernels.parallel.run_bands`) the CPU time of its busiest worker. That is
about the wall time the call takes with its cores to itself (it leaves out thread wake-up
latency, and cache contention from the other jobs still inflates it a little). It prints the
estimate and the measured wall time, medians over ``--repeats`` calls. Works on any checkout
with the same ``run_bands`` signature, so an old tree with its own venv can be measured the same
way. Not part of the test suite.
"""

from __future__ import annotations

import argparse
import os
import threading
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="heavy,profile",
                    help="comma-separated scene names of `splatsearch bench` (default heavy,profile)")
    ap.add_argument("--repeats", type=int, default=5, help="timed calls per measure (default 5)")
    args = ap.parse_args()

    import jax
    import warp as wp

    wp.config.quiet = True
    import splatsearch.rasterization as R
    from splatsearch import bench
    from splatsearch.kernels import parallel as par
    from splatsearch.kernels import pipeline as pl

    state = {"on": False, "worker0": 0.0, "crit": 0.0, "call": 0.0}
    run_bands = par.run_bands

    def timed_run_bands(bands, n_threads, fn, kernel=None, device=None, **kw):
        if not state["on"]:
            return run_bands(bands, n_threads, fn, kernel, device, **kw)
        per: dict[int, float] = {}
        lock = threading.Lock()

        def timed(w, b0, b1):
            c = time.thread_time()
            fn(w, b0, b1)
            with lock:
                per[w] = per.get(w, 0.0) + time.thread_time() - c

        run_bands(bands, n_threads, timed, kernel, device, **kw)
        state["worker0"] += per.get(0, 0.0)  # ran on the calling thread, counted in "call" too
        state["crit"] += max(per.values(), default=0.0)

    par.run_bands = timed_run_bands
    pl.run_bands = timed_run_bands

    def timed_call(f):
        def g(*a, **k):
            c = time.thread_time()
            try:
                return f(*a, **k)
            finally:
                state["call"] += time.thread_time() - c
        return g

    R._pl.rasterize_forward = timed_call(pl.rasterize_forward)
    R._pl.rasterize_backward = timed_call(pl.rasterize_backward)

    for name in args.scenes.split(","):
        for label, sc in bench.scene_makers()[name]():
            fwd, fwd_bwd, params = bench.make_render_fns(sc)
            res = {}
            for key, fn in (("fwd", fwd), ("fwd+bwd", fwd_bwd)):
                for _ in range(2):
                    jax.block_until_ready(fn(*params))
                ests, walls = [], []
                for _ in range(args.repeats):
                    state.update(on=True, worker0=0.0, crit=0.0, call=0.0)
                    t0 = time.perf_counter()
                    jax.block_until_ready(fn(*params))
                    walls.append(time.perf_counter() - t0)
                    state["on"] = False
                    ests.append(state["call"] - state["worker0"] + state["crit"])
                res[key] = (1e3 * float(np.median(ests)), 1e3 * float(np.median(walls)))
            print(f"{label}: load {os.getloadavg()[0]:.1f}; critical-path CPU ms (about the quiet wall time) / "
                  f"measured wall ms: forward {res['fwd'][0]:.1f} / {res['fwd'][1]:.1f}, forward + backward "
                  f"{res['fwd+bwd'][0]:.1f} / {res['fwd+bwd'][1]:.1f}", flush=True)


if __name__ == "__main__":
    main()
