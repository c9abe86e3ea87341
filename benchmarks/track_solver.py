"""Tracking solvers side by side: Adam (40 steps) vs Levenberg-Marquardt ("gn"), alternating in one process.

    python benchmarks/track_solver.py [--data sim,tum] [--seed 0] [--planar] [--map-frames 12]
                                      [--track-frames 8] [--rounds 2] [--gn-iters 8] [--gn-loss-tol TOL]

Same maps and frames as ``track_speed.py`` (a map fitted with ground-truth poses to the first
``--map-frames`` frames, the next ``--track-frames`` tracked against it frozen; simulator:
odometry-step initial pose with the odometry prior; TUM: the previous ground-truth pose). Each
frame is tracked by each solver in turn for ``--rounds`` rounds (first calls compile, untimed).
``--planar``: the simulator frames are tracked with ``planar=True`` as ``slam_eval.py sim --planar``
does (TUM is always 6-DoF). Prints load, per-frame process CPU seconds and wall seconds
(medians), iterations, and the pose errors against ground truth. Not part of the test suite.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="sim,tum", help="comma-separated subset of sim,tum (default both)")
    ap.add_argument("--seed", type=int, default=0, help="dev house of the simulator walk (default 0; never >= 1000)")
    ap.add_argument("--planar", action="store_true", help="track the simulator frames with planar=True")
    ap.add_argument("--map-frames", type=int, default=12, help="frames mapped with ground-truth poses (default 12)")
    ap.add_argument("--track-frames", type=int, default=8, help="frames tracked after them (default 8)")
    ap.add_argument("--rounds", type=int, default=2, help="alternating rounds over the tracked frames (default 2)")
    ap.add_argument("--gn-iters", type=int, default=8, help="most Levenberg-Marquardt iterations (default 8)")
    ap.add_argument("--gn-loss-tol", type=float, default=None,
                    help="GN stops after an accepted step that lowers the loss by less than this fraction "
                         "(default: TrackerConfig's gn_loss_tol)")
    ap.add_argument("--solvers", default="adam,gn", help="comma-separated subset of adam,gn (default both)")
    a = ap.parse_args(argv)
    data = a.data.split(",")
    solvers = a.solvers.split(",")
    if not data or any(d not in ("sim", "tum") for d in data):
        ap.error(f"--data takes a comma-separated subset of sim,tum, got {a.data!r}")
    if not solvers or any(s not in ("adam", "gn") for s in solvers):
        ap.error(f"--solvers takes a comma-separated subset of adam,gn, got {a.solvers!r}")
    if a.seed >= 1000:
        ap.error("seeds >= 1000 are evaluation houses: never tuned on")
    if a.map_frames < 1 or a.track_frames < 1 or a.rounds < 1 or a.gn_iters < 1:
        ap.error("--map-frames, --track-frames, --rounds and --gn-iters must be >= 1")
    if a.gn_loss_tol is None:
        from splatsearch.slam import TrackerConfig

        a.gn_loss_tol = TrackerConfig().gn_loss_tol
    if not a.gn_loss_tol >= 0:
        ap.error("--gn-loss-tol must be >= 0")
    if "tum" in data and a.map_frames + a.track_frames > 10:
        ap.error("the TUM set has 10 frames: --map-frames + --track-frames must be <= 10")
    from track_speed import _build

    from splatsearch import slam

    for name in data:
        gmap, todo, K, W, H, n_g = _build(name, a.seed, a.map_frames, a.track_frames)
        planar = a.planar and name == "sim"
        cfgs = {s: slam.TrackerConfig(solver=s, gn_iters=a.gn_iters, planar=planar, gn_loss_tol=a.gn_loss_tol)
                for s in solvers}

        def run(s, fr):
            rgb, depth, gt, init, prior = fr
            r = slam.track(gmap, rgb, depth, init, K, W, H, cfgs[s], prior_sigma=prior)
            ang, dist = slam.pose_distance(r.viewmat, gt)
            ang0, dist0 = slam.pose_distance(init, gt)
            return r, np.degrees(ang), 100 * dist, np.degrees(ang0), 100 * dist0

        for s in solvers:
            run(s, todo[0])
        rec = {s: [] for s in solvers}
        for _ in range(a.rounds):
            for fr in todo:
                for s in solvers:
                    r, ang, cm, ang0, cm0 = run(s, fr)
                    rec[s].append((r.cpu_seconds, r.seconds, r.steps, ang, cm, ang0, cm0, r.loss, r.status))
        print(f"== {name}{' planar' if planar else ''}: {W}x{H}, map {n_g} Gaussians, {len(todo)} frames x "
              f"{a.rounds} rounds, load {os.getloadavg()[0]:.2f}")
        x0 = np.array([v[5:7] for v in rec[solvers[0]]], np.float64)
        print(f"  initial error {x0[:, 0].mean():.3f} deg {x0[:, 1].mean():.3f} cm")
        for s in solvers:
            x = np.array([v[:5] + (v[7],) for v in rec[s]], np.float64)
            st = sorted({v[8] for v in rec[s]})
            print(f"  {s:5s} CPU-s/frame {np.median(x[:, 0]):.3f} (mean {x[:, 0].mean():.3f})  "
                  f"wall s/frame {np.median(x[:, 1]):.3f}  iters {x[:, 2].mean():.1f}  "
                  f"error {x[:, 3].mean():.3f} deg {x[:, 4].mean():.3f} cm (max {x[:, 4].max():.3f})  "
                  f"loss {x[:, 5].mean():.5f}  status {st}")
        if len(solvers) == 2:
            c = [np.array([v[0] for v in rec[s]]) for s in solvers]
            print(f"  {solvers[1]}/{solvers[0]} CPU-s per frame: {np.median(c[1] / c[0]):.3f} (median of paired frames)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
