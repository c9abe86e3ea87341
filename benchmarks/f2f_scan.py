"""OpenCV-only pass over simulator walks: how often the frame-to-frame step fails (no tracking, no map).

Mirrors ``SLAM``'s frame-to-frame chain (``slam._f2f_link_to``) with the default ``TrackerConfig``:
each raw frame is linked to the previous one by OpenCV RGB-D odometry (ICP limit 0.07 m, then the
retry's 0.15 m), reduced to a yaw-only step (planar) and gated against the noisy odometry's step.
A processed (training) frame gets the worst status of the links since the previous processed frame,
as ``summary.json``'s f2f counts do (held-out frames, every 8th, only extend the chain).

    python benchmarks/f2f_scan.py --seeds 3-40 [--frames 100] [--out scan.json] [--detail]

``--detail`` adds, per link, what it tells the tracker against the truth (OpenCV's, the odometry's
and the true distance along the odometry's direction of motion and yaw; ``link_detail``).

Dev houses only (seeds < 1000): evaluation houses are never scanned.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import cv2
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


def _yaw(step: np.ndarray, up_cam: np.ndarray) -> float:
    """The camera's turn (rad, right-handed about ``up_cam``, the world's vertical in the previous
    camera's frame) over a (4, 4) world-to-camera step (whose own rotation is the inverse turn)."""
    w = cv2.Rodrigues(np.asarray(step, np.float64)[:3, :3])[0].ravel()
    return -float(w @ (up_cam / np.linalg.norm(up_cam)))


def link_detail(step: np.ndarray | None, odo: np.ndarray, true: np.ndarray, up_cam: np.ndarray) -> dict:
    """What a link tells the tracker against the truth, all along the wheel odometry's direction of
    motion in the previous camera's frame (m) and about the vertical (rad): ``cv_along`` (OpenCV's
    displacement, what the along-path prior is given; None when it failed), ``odo_along`` (the
    odometry's distance), ``true_along`` (the true displacement's component); ``cv_yaw`` / ``odo_yaw``
    / ``true_yaw`` the same for the heading change. Steps (4, 4) world-to-camera of the new frame
    times camera-to-world of the previous one."""
    d_odo = odometry_f2f.camera_displacement(odo)
    dist = float(np.linalg.norm(d_odo))
    u = d_odo / dist if dist >= 1e-3 else np.zeros(3)
    out = {"odo_along": dist, "true_along": float(odometry_f2f.camera_displacement(true) @ u),
           "cv_along": None, "odo_yaw": _yaw(odo, up_cam), "true_yaw": _yaw(true, up_cam), "cv_yaw": None}
    if step is not None:
        out["cv_along"] = float(odometry_f2f.camera_displacement(step) @ u)
        out["cv_yaw"] = _yaw(step, up_cam)
    return out


def scan_walk(seed: int, frames: int = 100, holdout_every: int = 8, detail: bool = False) -> dict:
    """Per-frame OpenCV link status of one dev house walk (dict: per-link and per-processed-frame
    counts; with ``detail``, ``link_detail`` per link (index 0: None), see :func:`link_detail`)."""
    if seed >= 1000:
        raise ValueError("evaluation houses (seed >= 1000) are not scanned")
    tc = TrackerConfig()
    seq = datasets.sim_walk(seed, frames, 320, 240, odometry_seed=seed)
    odom = np.asarray(seq.odometry, np.float64)
    gt = np.asarray(seq.gt_viewmats(), np.float64) if detail else None
    links: list[str] = ["none"]
    details: list[dict | None] = [None]
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
        if detail:
            up = odom[i - 1][:3, 2]
            d = link_detail(step, odo, gt[i] @ np.linalg.inv(gt[i - 1]), up)
            details.append({"status": status, "max_depth_diff": md, **d})
    train, _ = split_holdout(len(seq), holdout_every)
    rank = {"accepted": 1, "rejected": 2, "failed": 3}
    per_frame, prev = {}, None
    for i in train:
        if prev is not None:
            worst = max(links[prev + 1:i + 1], key=rank.__getitem__)
            per_frame[i] = worst
        prev = i
    count = lambda xs: {k: sum(1 for x in xs if x == k) for k in ("accepted", "rejected", "failed")}  # noqa: E731
    out = {"seed": seed, "links": links, "frames": per_frame, "link_counts": count(links[1:]),
           "frame_counts": count(per_frame.values())}
    if detail:
        out["link_detail"] = details
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", required=True, help="dev house seeds, e.g. 3-40 or 3,5,7")
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--out", default=None, help="write every walk's per-frame statuses here (JSON)")
    p.add_argument("--detail", action="store_true",
                   help="also record per link OpenCV's / the odometry's / the true along-path distance and yaw")
    a = p.parse_args(argv)
    seeds = _seeds(a.seeds)
    if any(s >= 1000 for s in seeds):
        p.error("dev houses only (seeds < 1000)")
    rows = []
    for s in seeds:
        t = time.process_time()
        r = scan_walk(s, a.frames, detail=a.detail)
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
