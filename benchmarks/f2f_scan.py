"""OpenCV-only pass over simulator walks: how often the frame-to-frame step fails (no tracking, no map).

Mirrors ``SLAM``'s frame-to-frame chain (``slam._f2f_link_to``) with the default ``TrackerConfig``:
each raw frame is linked to the previous one by OpenCV RGB-D odometry (ICP limit 0.07 m, then the
retry's 0.15 m), reduced to a yaw-only step (planar) and gated against the noisy odometry's step.
A processed (training) frame gets the worst status of the links since the previous processed frame,
as ``summary.json``'s f2f counts do (held-out frames, every 8th, only extend the chain).

    python benchmarks/f2f_scan.py --seeds 3-40 [--frames 100] [--out scan.json]

Dev houses only (seeds < 1000): evaluation houses are never scanned.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from splatsearch import datasets, odometry_f2f
from splatsearch.map_job import split_holdout
from splatsearch.slam import TrackerConfig


def _seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out += list(range(int(lo), int(hi or lo) + 1))
    return out


def scan_walk(seed: int, frames: int = 100, holdout_every: int = 8) -> dict:
    """Per-frame OpenCV link status of one dev house walk (dict: per-link and per-processed-frame counts)."""
    if seed >= 1000:
        raise ValueError("evaluation houses (seed >= 1000) are not scanned")
    tc = TrackerConfig()
    seq = datasets.sim_walk(seed, frames, 320, 240, odometry_seed=seed)
    odom = np.asarray(seq.odometry, np.float64)
    links: list[str] = ["none"]
    for i in range(1, len(seq)):
        a, b = seq.frames[i - 1], seq.frames[i]
        odo = odom[i] @ np.linalg.inv(odom[i - 1])
        sr, st = tc.prior_sigma(odo)
        status = "failed"
        for md in [tc.f2f_max_depth_diff] + ([tc.f2f_retry_depth_diff] if tc.f2f_retry_depth_diff else []):
            step = odometry_f2f.f2f_step(a.rgb, a.depth, b.rgb, b.depth, seq.K, max_depth_diff=md)
            if step is not None:
                step = odometry_f2f.planar_yaw_only(step, odom[i - 1][:3, 2])
            status = "failed" if step is None else ("accepted" if odometry_f2f.gate_step(step, odo, sr, st)
                                                    else "rejected")
            if status == "accepted":
                break
        links.append(status)
    train, _ = split_holdout(len(seq), holdout_every)
    rank = {"accepted": 1, "rejected": 2, "failed": 3}
    per_frame, prev = {}, None
    for i in train:
        if prev is not None:
            worst = max(links[prev + 1:i + 1], key=rank.__getitem__)
            per_frame[i] = worst
        prev = i
    count = lambda xs: {k: sum(1 for x in xs if x == k) for k in ("accepted", "rejected", "failed")}  # noqa: E731
    return {"seed": seed, "links": links, "frames": per_frame, "link_counts": count(links[1:]),
            "frame_counts": count(per_frame.values())}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", required=True, help="dev house seeds, e.g. 3-40 or 3,5,7")
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--out", default=None, help="write every walk's per-frame statuses here (JSON)")
    a = p.parse_args(argv)
    seeds = _seeds(a.seeds)
    if any(s >= 1000 for s in seeds):
        p.error("dev houses only (seeds < 1000)")
    rows = []
    for s in seeds:
        t = time.process_time()
        r = scan_walk(s, a.frames)
        fc = r["frame_counts"]
        n = sum(fc.values())
        print(f"house {s}: frames acc/rej/fail {fc['accepted']}/{fc['rejected']}/{fc['failed']} "
              f"(fail {fc['failed'] / max(n, 1):.2f}), links {r['link_counts']}, {time.process_time() - t:.1f} CPU-s",
              flush=True)
        rows.append(r)
        if a.out:
            with open(a.out, "w") as f:
                json.dump(rows, f)
    return 0


if __name__ == "__main__":
    sys.exit(main())
