"""Map a whole RGB-D sequence (what ``splatsearch map`` runs): track and/or map every training
frame, refine, evaluate on training and held-out frames, compute ATE, write the outputs.

Outputs in ``out``: ``map.ply``, ``map.npz``, ``trajectory.txt`` (estimated poses, TUM format),
``summary.json`` (metrics, ATE, per-frame timing split into tracking and mapping, per-frame
status, and the trajectory lines); every file is written atomically.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from splatsearch import io
from splatsearch.datasets.base import RGBDSequence
from splatsearch.mapper import Frame, MapperConfig
from splatsearch.slam import SLAM, FrameResult, TrackerConfig
from splatsearch.trajectory import ate, tum_lines, write_tum


@dataclass
class MapJob:
    """Settings of :func:`map_sequence`.

    track: estimate poses (first pose: ground truth when known, else identity). use_odometry:
    use the sequence's odometry as the tracking prior. holdout_every: hold out one frame in N
    (the middle one of each block) for evaluation (0: none). refine: Adam steps over the
    keyframes after the last frame. gt_prior: with ``track``, start each frame's tracking from
    its ground-truth pose (pose refinement of a trajectory that is not pixel-exact).
    """

    mapper: MapperConfig
    tracker: TrackerConfig
    track: bool = False
    use_odometry: bool = False
    holdout_every: int = 8
    refine: int = 0
    gt_prior: bool = False


def split_holdout(n: int, every: int) -> tuple[list[int], list[int]]:
    """(training indices, held-out indices) of n frames, holding out the middle of each block of
    ``every`` frames (every < 2: none held out)."""
    if every < 2:
        return list(range(n)), []
    held = [i for i in range(n) if i % every == every // 2]
    return [i for i in range(n) if i % every != every // 2], held


def map_sequence(seq: RGBDSequence, job: MapJob, out: str | None = None,
                 progress: Callable[[FrameResult, int, int], None] | None = None) -> tuple[SLAM, dict]:
    """Run ``job`` over ``seq``; returns (the SLAM object, the summary dict). A KeyboardInterrupt
    stops at the current frame; the summary says so and everything built so far is written."""
    if not job.track and not seq.has_gt:
        raise ValueError(f"{seq.path}: no ground-truth poses; map it with tracking (--track)")
    if job.gt_prior and not seq.has_gt:
        raise ValueError(f"{seq.path}: gt_prior needs ground-truth poses")
    if job.use_odometry and seq.odometry is None:
        raise ValueError(f"{seq.path}: the sequence has no odometry")
    train, held = split_holdout(len(seq), job.holdout_every)
    slam = SLAM(seq.K, seq.width, seq.height, job.mapper, job.tracker, track=job.track)
    interrupted = False
    t_start = time.perf_counter()
    try:
        held_set = set(held)
        k = 0
        for i in range(len(seq)):
            f = seq.frames[i]
            if i in held_set:
                # a held-out view is never mapped, but it links the frame-to-frame chain
                if job.track and job.use_odometry:
                    slam.observe(f.rgb, f.depth, seq.odometry[i])
                continue
            odo = seq.odometry[i] if job.use_odometry else None
            given = f.viewmat if (not job.track or k == 0) else None
            prior = f.viewmat if (job.track and job.gt_prior) else None
            r = slam.process(f.rgb, f.depth, given, odometry=odo, prior=prior)
            k += 1
            if progress is not None:
                progress(r, k, len(train))
        if job.refine:
            slam.refine(job.refine)
    except KeyboardInterrupt:
        interrupted = True
    wall = time.perf_counter() - t_start
    done = train[: len(slam.results)]
    est = slam.trajectory()
    summary: dict = {
        "data": seq.path, "format": seq.format, "resolution": [seq.width, seq.height], "notes": seq.notes,
        "frames_total": len(seq), "frames_processed": len(done),
        "frames_mapped": sum(r.mapped for r in slam.results), "interrupted": interrupted,
        "gaussians": slam.mapper.map.n_active, "tracking": job.track, "odometry_prior": job.use_odometry,
        "iters_per_frame": job.mapper.iters, "tracking_iters": job.tracker.iters if job.track else 0,
        "refine_iters": job.refine, "wall_s": wall,
    }
    t_tr = [r.t_track for r in slam.results if r.track is not None]
    t_map = [r.t_map for r in slam.results if r.mapped]
    summary["timing"] = {
        "median_track_s": float(np.median(t_tr)) if t_tr else None,
        "median_map_s": float(np.median(t_map)) if t_map else None,
        "median_track_cpu_s": float(np.median([r.track.cpu_seconds for r in slam.results if r.track])) if t_tr
        else None,
        "mean_track_s": float(np.mean(t_tr)) if t_tr else None, "mean_map_s": float(np.mean(t_map)) if t_map else None,
        "mean_track_cpu_s": float(np.mean([r.track.cpu_seconds for r in slam.results if r.track])) if t_tr
        else None,
        "mean_track_steps": float(np.mean([r.track.steps for r in slam.results if r.track])) if t_tr else None,
        "per_frame": [{"frame": int(i), "status": r.status, "track_s": round(r.t_track, 4), "map_s": round(r.t_map, 4),
                       "track_status": r.track.status if r.track else None,
                       "track_cpu_s": round(r.track.cpu_seconds, 4) if r.track else None,
                       "track_steps": r.track.steps if r.track else None,
                       "track_loss": _finite(r.track.loss) if r.track else None,
                       "track_rot_info": _finite(r.track.rot_info) if r.track else None,
                       "track_fwd_info": _finite(r.track.fwd_info) if r.track else None,
                       "track_fade": _finite(r.track.fade) if r.track else None, "f2f": r.f2f,
                       # the tracker's pose before the mapper's pose refinement moved it
                       "track_viewmat": [round(float(v), 7) for v in np.asarray(r.track.viewmat).ravel()]
                       if r.track is not None and r.track.viewmat is not None else None}
                      for i, r in zip(done, slam.results)],
    }
    f2f = [r.f2f for r in slam.results if r.f2f is not None]
    summary["f2f"] = {s: f2f.count(s) for s in ("accepted", "rejected", "failed")} if f2f else None
    bad = [(int(i), r.status) for i, r in zip(done, slam.results) if r.status.startswith("skipped")]
    summary["bad_frames"] = bad
    # evaluation: training views at the estimated poses (what the map was fitted to), held-out
    # views at their ground-truth poses (the map lives in the first frame's ground-truth frame)
    # and, when tracking, at poses tracked against the final map (held_out_tracked)
    ok = [(i, p) for i, p, r in zip(done, est, slam.results) if r.mapped]
    summary["train"] = slam.mapper.evaluate([Frame(seq.frames[i].rgb, seq.frames[i].depth, p) for i, p in ok]) \
        if ok else None
    if job.mapper.exposure and slam.mapper.keyframes:
        summary["train_keyframes_exposure"] = slam.mapper.evaluate(slam.mapper.keyframes, exposure=True)
    if seq.has_gt:
        gt = seq.gt_viewmats()
        ok_gt = [i for i, _ in ok if np.all(np.isfinite(gt[i]))]
        if job.track and ok_gt:
            summary["train_at_gt_pose"] = slam.mapper.evaluate([seq.frames[i] for i in ok_gt])
        held_ok = [seq.frames[i] for i in held if np.all(np.isfinite(gt[i]))]
        summary["held_out"] = slam.mapper.evaluate(held_ok) if held_ok and ok else None
        if job.track and held_ok and ok:
            summary["held_out_tracked"] = slam.mapper.evaluate(_localized(slam, seq, job, held, done, est, gt))
        if len(done) >= 2:
            a = ate(est, gt[done])
            summary["ate"] = {k: a[k] for k in ("rmse", "mean", "median", "max", "n")}
            if job.use_odometry:
                o = ate(seq.odometry[done], gt[done])
                summary["ate_odometry"] = {k: o[k] for k in ("rmse", "mean", "median", "max", "n")}
    else:
        summary["held_out"] = None
    ts = np.asarray(seq.timestamps)[done]
    summary["trajectory_tum"] = tum_lines(ts, est)
    if out is not None:
        os.makedirs(out, exist_ok=True)
        io.save_ply(slam.mapper.map, os.path.join(out, "map.ply"))
        io.save_npz(slam.mapper.map, os.path.join(out, "map.npz"), K=seq.K, size=np.array([seq.width, seq.height]))
        write_tum(os.path.join(out, "trajectory.txt"), ts, est)
        io.atomic_write_bytes(os.path.join(out, "summary.json"), json.dumps(summary, indent=1).encode())
    return slam, summary


def _localized(slam: SLAM, seq: RGBDSequence, job: MapJob, held: list[int], done: list[int], est: np.ndarray,
               gt: np.ndarray) -> list[Frame]:
    """Held-out frames at poses tracked against the final map, each started from the last earlier
    training frame's estimate (moved by the odometry's step when the job uses odometry). A tracked
    map lives in its own slightly drifted frame; this scores the map where the robot would place
    the view, apart from the trajectory's error (SplaTAM renders every frame at its estimate)."""
    out = []
    for i in held:
        if not np.all(np.isfinite(gt[i])):
            continue
        prev = [(j, p) for j, p in zip(done, est) if j < i and np.all(np.isfinite(p))]
        if not prev:
            continue
        j, init = prev[-1][0], prev[-1][1].astype(np.float64)
        if job.use_odometry:
            init = seq.odometry[i].astype(np.float64) @ np.linalg.inv(seq.odometry[j].astype(np.float64)) @ init
        f = seq.frames[i]
        out.append(Frame(f.rgb, f.depth, slam.localize(f.rgb, f.depth, init.astype(np.float32))))
    return out


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None
