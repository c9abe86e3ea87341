"""Tracking cost and accuracy of two tracker variants, alternating frame by frame in one process.

    python benchmarks/track_speed.py [--compare backward|jacobian] [--data sim,tum] [--map-frames 12]
                                     [--track-frames 8] [--rounds 2]

For each data set a map is fitted with ground-truth poses to the first ``--map-frames`` frames
(simulator: dev house ``--seed`` at 320x240 with the SIM mapper settings of ``slam_eval.py``;
TUM: the shared fr1/xyz frames at half size, 320x240, with the REAL settings), then the next
``--track-frames`` frames are tracked against that frozen map with the default
:class:`~splatsearch.slam.TrackerConfig`, once with each variant. ``--compare backward`` (default;
the 40-step Adam solver + odometry prior, whose cost is mostly the backward):

- ``all``: ``rasterize(..., differentiable="all")``, every Gaussian's gradient formed (before);
- ``viewmat``: ``rasterize(..., differentiable="viewmat")``, the pose-only backward (now the default).

``--compare jacobian``: the default Levenberg-Marquardt solver (6 DoF) with
``TrackerConfig.jacobian`` ``finite-difference`` (6 extra renders a frame) and ``analytic``; also
prints the forward renders a frame (1 at the start + 6 differences (finite-difference only) + 1 per
step, rejected ones included; a step's backward runs only when the next step uses its gradient).

The two alternate frame by frame for ``--rounds`` rounds (the first call of each compiles and is
not timed). Initial pose: simulator, the previous ground-truth pose moved by the noisy odometry's
step (with the odometry prior, as :class:`~splatsearch.slam.SLAM` does); TUM, the previous
ground-truth pose (no prior). Prints the machine load, per-frame and per-step process CPU seconds
and wall seconds (medians), and the pose errors against ground truth of both. Not part of the
test suite.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
TUM = os.path.join(HERE, "..", "..", "shared", "data", "tum_fr1_xyz_first10")
COMPARE = {"backward": ("all", "viewmat"), "jacobian": ("finite-difference", "analytic")}


def _build(name: str, seed: int, n_map: int, n_track: int):
    """(map, frames to track [(rgb, depth, gt, init, prior_sigma)], K, W, H)."""
    sys.path.insert(0, HERE)
    from slam_eval import REAL, SIM

    from splatsearch import datasets
    from splatsearch.mapper import Mapper, MapperConfig
    from splatsearch.slam import TrackerConfig

    if name == "sim":
        seq = datasets.sim_walk(seed, n_map + n_track, 320, 240)
        cfg = SIM
    else:
        if not os.path.isdir(TUM):
            raise SystemExit(f"{TUM} not present")
        seq = datasets.load_sequence(TUM, downscale=2)
        cfg = REAL
    if n_map + n_track > len(seq.frames):
        raise SystemExit(f"{name}: {len(seq.frames)} frames, fewer than --map-frames + --track-frames")
    m = Mapper(seq.K, seq.width, seq.height, MapperConfig(**cfg))
    for f in seq.frames[:n_map]:
        m.update(f.rgb, f.depth, f.viewmat)
    tcfg = TrackerConfig()
    todo = []
    for i in range(n_map, n_map + n_track):
        f, prev = seq.frames[i], seq.frames[i - 1].viewmat.astype(np.float64)
        if getattr(seq, "odometry", None) is not None:
            step = seq.odometry[i].astype(np.float64) @ np.linalg.inv(seq.odometry[i - 1].astype(np.float64))
            todo.append((f.rgb, f.depth, f.viewmat, (step @ prev).astype(np.float32), tcfg.prior_sigma(step)))
        else:
            todo.append((f.rgb, f.depth, f.viewmat, prev.astype(np.float32), None))
    return m.map, todo, seq.K, seq.width, seq.height, m.map.n_active


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--compare", default="backward", choices=sorted(COMPARE),
                    help="what is compared: the rasterizer backward (Adam tracker) or the Levenberg-Marquardt "
                         "Jacobian (default backward)")
    ap.add_argument("--data", default="sim,tum", help="comma-separated subset of sim,tum (default both)")
    ap.add_argument("--seed", type=int, default=0, help="dev house of the simulator walk (default 0; never >= 1000)")
    ap.add_argument("--map-frames", type=int, default=12, help="frames mapped with ground-truth poses (default 12)")
    ap.add_argument("--track-frames", type=int, default=8, help="frames tracked after them (default 8)")
    ap.add_argument("--rounds", type=int, default=2, help="alternating rounds over the tracked frames (default 2)")
    a = ap.parse_args(argv)
    data = a.data.split(",")
    if not data or any(d not in ("sim", "tum") for d in data):
        ap.error(f"--data takes a comma-separated subset of sim,tum, got {a.data!r}")
    if a.seed >= 1000:
        ap.error("seeds >= 1000 are evaluation houses: never tuned on")
    if a.map_frames < 1 or a.track_frames < 1 or a.rounds < 1:
        ap.error("--map-frames, --track-frames and --rounds must be >= 1")
    if "tum" in data and a.map_frames + a.track_frames > 10:
        ap.error("the TUM set has 10 frames: --map-frames + --track-frames must be <= 10")
    from splatsearch import slam

    MODES = COMPARE[a.compare]
    caches = {mode: {} for mode in MODES}

    def run(mode, gmap, fr, K, W, H):
        rgb, depth, gt, init, prior = fr
        if a.compare == "jacobian":
            r = slam.track(gmap, rgb, depth, init, K, W, H, solver="gn", jacobian=mode, prior_sigma=prior)
        else:
            slam._TRACK_DIFF, slam._TRACK_FNS = mode, caches[mode]  # one compiled tracker per backward
            # the 40-step Adam tracker, whose cost is mostly the backward being compared
            r = slam.track(gmap, rgb, depth, init, K, W, H, solver="adam", prior_sigma=prior)
        ang, dist = slam.pose_distance(r.viewmat, gt)
        return r, np.degrees(ang), 100 * dist

    for name in data:
        gmap, todo, K, W, H, n_g = _build(name, a.seed, a.map_frames, a.track_frames)
        for mode in MODES:  # compile both outside the timing
            run(mode, gmap, todo[0], K, W, H)
        rec = {mode: [] for mode in MODES}
        for _ in range(a.rounds):
            for fr in todo:
                for mode in MODES:
                    r, ang, cm = run(mode, gmap, fr, K, W, H)
                    rec[mode].append((r.cpu_seconds, r.seconds, r.steps, ang, cm, r.status))
        print(f"== {name}: {W}x{H}, map {n_g} Gaussians, {len(todo)} frames x {a.rounds} rounds, "
              f"load {os.getloadavg()[0]:.2f}")
        for mode in MODES:
            x = np.array([v[:5] for v in rec[mode]], np.float64)
            st = sorted({v[5] for v in rec[mode]})
            renders = (f"  forward renders/frame {1 + x[:, 2].mean() + (6 if mode == 'finite-difference' else 0):.1f}"
                       if a.compare == "jacobian" else "")
            print(f"  {mode:8s} CPU-s/frame {np.median(x[:, 0]):.3f} (mean {x[:, 0].mean():.3f})  "
                  f"wall s/frame {np.median(x[:, 1]):.3f}  steps {x[:, 2].mean():.1f}  "
                  f"CPU-ms/step {1e3 * np.median(x[:, 0] / np.maximum(x[:, 2], 1)):.1f}  "
                  f"error {x[:, 3].mean():.3f} deg {x[:, 4].mean():.3f} cm  status {st}{renders}")
        ca = np.array([v[0] for v in rec[MODES[0]]])
        cv = np.array([v[0] for v in rec[MODES[1]]])
        print(f"  {MODES[1]}/{MODES[0]} CPU-s per frame: {np.median(cv / ca):.3f} (median of paired frames)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
