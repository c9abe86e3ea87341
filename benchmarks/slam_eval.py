"""Tracking and real-sensor mapping targets of issue 24, one JSON line per run.

    python benchmarks/slam_eval.py tum   [--downscale 2] [--out runs/slam_eval]   # GT poses vs --track
    python benchmarks/slam_eval.py sim   [--frames 100] [--seed 0]               # noisy odometry walk
    python benchmarks/slam_eval.py speed [--frames 10]                           # tracking s/frame

``tum``: the 10 shared TUM fr1/xyz frames; (a) ground-truth poses, every frame trained; (b)
``--track`` from the first pose, every frame trained (ATE, PSNR at the tracked poses and at the
ground-truth poses); (c) ground-truth poses with every 5th frame held out (held-out PSNR).
``sim``: a walk through dev house ``--seed`` (an evaluation house, seed >= 1000, only with
``--evaluation``, for the held-out report with settled defaults) with noisy odometry:
ground-truth poses, and tracking with the odometry prior (ATE of the raw odometry beside it).
``speed``: tracking seconds per frame at 320x240 on this machine (load printed beside it).

Every run appends its summary (without per-frame lists) to ``OUT/results.jsonl``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from splatsearch import datasets
from splatsearch.map_job import MapJob, map_sequence
from splatsearch.mapper import MapperConfig
from splatsearch.slam import JACOBIANS, SOLVERS, TrackerConfig, parse_lateral_sigma
from splatsearch.trajectory import frame_errors, read_tum

TUM = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "tum_fr1_xyz_first10")

#: Real-sensor mapping settings (see docs/mapping.md for how they were chosen).
#: Stop 45: per-frame exposure on (the plain render drops 0.04 dB, the render with each frame's fitted
#: exposure rises 0.4 dB) and 500 refinement steps (200: 23.24 dB with exposure applied, 400: 23.95,
#: 500: 24.05, 800: 23.77; docs/results.md, "Stop 45, issue 24").
REAL = dict(iters=30, first_iters=60, stride=2, pixel_scale=2.0, fill_holes=True, keyframe_every=1, lambda_g=0.3,
            lr={"means": 2e-4, "log_scales": 5e-3, "quats": 1e-3, "opacity_logits": 5e-2, "colors": 1e-2},
            initial_capacity=1 << 15, exposure=True)
REAL_REFINE = 500
# pose_lr_trans: with the along-path frame-to-frame prior (the tracker's default since stop 46) the keyframe
# pose refinement's default 2e-4 m step moves frames back along the path toward the map's drift
SIM = dict(iters=15, first_iters=40, stride=3, pixel_scale=2.0, initial_capacity=1 << 15, pose_lr_trans=2e-5)


_SET: dict = {}  # --mapper-set overrides, recorded with every run


def _load():
    return os.getloadavg()[0]


def _brief(s: dict) -> dict:
    out = {k: v for k, v in s.items() if k not in ("trajectory_tum", "notes")}
    t = dict(out["timing"])
    t.pop("per_frame")
    out["timing"] = t
    out["statuses"] = {}
    for r in s["timing"]["per_frame"]:
        key = r["status"] + ("/" + r["track_status"] if r["track_status"] else "")
        out["statuses"][key] = out["statuses"].get(key, 0) + 1
    return out


FRAME_ERROR_COLUMNS = ("frame", "status", "f2f", "error_cm", "along_cm", "across_cm", "yaw_deg",
                       "track_error_cm", "track_along_cm", "track_across_cm", "track_yaw_deg")


def frame_error_rows(summary: dict, est, gt) -> list[dict]:
    """One row (FRAME_ERROR_COLUMNS) per processed frame of a run with ground truth: the final
    pose's error after the ATE alignment (cm; along / left of the true viewing direction; yaw in
    degrees) and the same for the tracker's pose before the mapper's pose refinement moved it
    (``track_*``, under the final trajectory's alignment; the final pose where none was logged).
    ``summary``: map_sequence's; ``est`` (N, 4, 4) the run's trajectory; ``gt`` (N, 4, 4) the truth
    of the same frames."""
    pf = summary["timing"]["per_frame"]
    est = np.asarray(est, np.float64)
    trk = np.array([np.array(r["track_viewmat"], np.float64).reshape(4, 4) if r.get("track_viewmat") else e
                    for r, e in zip(pf, est)])
    fe = frame_errors(est, gt)
    ft = frame_errors(trk, gt, alignment=(fe["R"], fe["t"]))
    return [{"frame": r["frame"], "status": r["status"], "f2f": r.get("f2f"),
             "error_cm": 100 * fe["error"][k], "along_cm": 100 * fe["along"][k], "across_cm": 100 * fe["across"][k],
             "yaw_deg": float(np.degrees(fe["yaw"][k])), "track_error_cm": 100 * ft["error"][k],
             "track_along_cm": 100 * ft["along"][k], "track_across_cm": 100 * ft["across"][k],
             "track_yaw_deg": float(np.degrees(ft["yaw"][k]))} for k, r in enumerate(pf)]


def write_frame_errors(path: str, rows: list[dict]) -> None:
    """``rows`` (frame_error_rows) as a tab-separated file with a header line."""
    with open(path, "w") as f:
        f.write("\t".join(FRAME_ERROR_COLUMNS) + "\n")
        for r in rows:
            f.write("\t".join(f"{r[c]:.4f}" if isinstance(r[c], float) else str(r[c]) for c in FRAME_ERROR_COLUMNS)
                    + "\n")


def _run(name: str, seq, job: MapJob, out: str) -> dict:
    load0 = _load()
    t0 = time.perf_counter()
    slam, summary = map_sequence(seq, job, os.path.join(out, name))
    if "ate" in summary and not summary["interrupted"]:
        # where the ATE comes from, frame by frame (frame_errors.tsv beside summary.json)
        done = [r["frame"] for r in summary["timing"]["per_frame"]]
        write_frame_errors(os.path.join(out, name, "frame_errors.tsv"),
                           frame_error_rows(summary, slam.trajectory(), seq.gt_viewmats()[done]))
    rec = {"run": name, "mapper_set": dict(_SET), "load_start": load0, "load_end": _load(), "cpus": os.cpu_count(),
           "seconds": time.perf_counter() - t0, **_brief(summary)}
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, "results.jsonl"), "a") as f:
        f.write(json.dumps(rec) + "\n")
    ev = summary.get("train") or {}
    ho = summary.get("held_out") or {}
    hot = summary.get("held_out_tracked") or {}
    print(f"{name}: train PSNR {ev.get('psnr', float('nan')):.2f} dB, held-out {ho.get('psnr', float('nan')):.2f} "
          f"(at tracked poses {hot.get('psnr', float('nan')):.2f}), "
          f"ATE {100 * summary.get('ate', {}).get('rmse', float('nan')):.2f} cm, "
          f"track {rec['timing']['median_track_s']} s, map {rec['timing']['median_map_s']} s, "
          f"load {load0:.1f}->{rec['load_end']:.1f}"
          + (f", odometry ATE {100 * summary['ate_odometry']['rmse']:.2f} cm" if "ate_odometry" in summary else "")
          + (f", f2f {summary['f2f']}" if summary.get("f2f") else "")
          + (f", keyframes with exposure {summary['train_keyframes_exposure']['psnr']:.2f} dB"
             if "train_keyframes_exposure" in summary else ""), flush=True)
    return rec


def _lateral(text: str) -> float | None:
    try:
        return parse_lateral_sigma(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _opt_float(text: str) -> float | None:
    """A float, or "off" / "none" (None: the setting is off)."""
    if text.strip().lower() in ("off", "none"):
        return None
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a number or 'off', got {text!r}") from None


def _opt_count(text: str) -> int | None:
    """An integer >= 1, or "off" / "none" (None: the setting is off)."""
    if text.strip().lower() in ("off", "none"):
        return None
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"an integer >= 1 or 'off', got {text!r}")
    return n


def _default(value) -> str:
    """A help text's default: the value, or 'off' for None."""
    return "off" if value is None else f"{value:g}"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("what", choices=["tum", "sim", "speed", "frame-errors"],
                   help="frame-errors: write frame_errors.tsv for an earlier sim run's folder (--out RUN_DIR, its "
                        "--seed and --frames), no mapping")
    p.add_argument("--downscale", type=int, default=2, help="TUM image size divisor (default 2: 320x240)")
    p.add_argument("--frames", type=int, default=100, help="simulator walk length (default 100)")
    p.add_argument("--seed", type=int, default=0, help="dev house seed (default 0; >= 1000 only with --evaluation)")
    p.add_argument("--evaluation", action="store_true",
                   help="allow an evaluation house (--seed >= 1000): only for the one run with settled defaults "
                        "that is reported as held-out, never for tuning")
    d = TrackerConfig()
    p.add_argument("--track-solver", default=d.solver, choices=SOLVERS,
                   help=f"tracking solver: adam (--track-iters steps) or gn (Levenberg-Marquardt, "
                        f"--track-gn-iters steps; default {d.solver})")
    p.add_argument("--track-jacobian", default=d.jacobian, choices=JACOBIANS,
                   help=f"with --track-solver gn: the pose Jacobian, analytic (one render) or finite-difference "
                        f"(one render per pose parameter; default {d.jacobian})")
    p.add_argument("--track-gn-iters", type=int, default=d.gn_iters,
                   help=f"most Levenberg-Marquardt steps per frame with --track-solver gn (default {d.gn_iters})")
    p.add_argument("--track-gn-loss-tol", type=float, default=d.gn_loss_tol,
                   help="with --track-solver gn: stop after an accepted step that lowers the loss by less than "
                        f"this fraction (0: never; default {d.gn_loss_tol:g})")
    p.add_argument("--track-iters", type=int, default=d.iters,
                   help=f"most tracking Adam steps per frame (default {d.iters})")
    p.add_argument("--track-coarse-iters", type=int, default=d.coarse_iters,
                   help=f"most coarse-stage tracking steps (default {d.coarse_iters})")
    p.add_argument("--track-patience", type=int, default=d.patience,
                   help=f"early-stop patience of a tracking stage (0: off; default {d.patience})")
    p.add_argument("--prior-weight", type=float, default=d.prior_weight,
                   help=f"odometry prior weight (default {d.prior_weight:g})")
    p.add_argument("--prior-rot-sigma", type=float, default=d.prior_rot_sigma,
                   help=f"odometry prior's rotation sigma in rad per frame (default {d.prior_rot_sigma:g})")
    p.add_argument("--prior-info-max", type=float, default=d.prior_info_max,
                   help="with --track-solver gn: raise the odometry prior's rotation precision by up to this "
                        "factor on frames whose image fixes the rotation less than the recent frames' median "
                        f"(1: off; default {d.prior_info_max:g})")
    p.add_argument("--map-min-info", type=float, default=d.map_min_info,
                   help="with --track-solver gn: track but do not map a frame whose image fixes the rotation less "
                        f"than this fraction of the recent frames' median (0: off; default {d.map_min_info:g})")
    p.add_argument("--map-skip-max", type=int, default=d.map_skip_max,
                   help=f"with --map-min-info: most frames in a row left out of the map (default {d.map_skip_max})")
    p.add_argument("--prior-lateral", default=d.prior_lateral_sigma, type=_lateral,
                   help="odometry prior's sigma across the direction moved, as a fraction of the distance, or "
                        f"'off' (the same as along it; default {d.prior_lateral_sigma})")
    p.add_argument("--f2f-prior", action=argparse.BooleanOptionalAction, default=d.f2f_prior,
                   help="frame-to-frame rotation prior from OpenCV's RGB-D odometry between consecutive raw "
                        f"frames, gated by the odometry (default {'on' if d.f2f_prior else 'off'})")
    p.add_argument("--f2f-rot-sigma", type=float, default=d.f2f_rot_sigma,
                   help=f"rotation sigma (rad) of an accepted frame-to-frame step (default {d.f2f_rot_sigma:g})")
    p.add_argument("--f2f-max-depth-diff", type=float, default=d.f2f_max_depth_diff,
                   help="OpenCV's ICP correspondence depth limit (m) of the frame-to-frame odometry "
                        f"(default {d.f2f_max_depth_diff:g})")
    p.add_argument("--f2f-trans-sigma", type=_opt_float, default=d.f2f_trans_sigma,
                   help="also take an accepted frame-to-frame step's displacement, with this sigma in m "
                        f"or 'off' (default {_default(d.f2f_trans_sigma)}; off: rotation only)")
    p.add_argument("--f2f-along-sigma", type=_opt_float, default=d.f2f_along_sigma,
                   help="take only an accepted frame-to-frame step's displacement along the odometry's direction "
                        f"of motion, with this sigma in m, or 'off' (default {_default(d.f2f_along_sigma)})")
    p.add_argument("--f2f-along-fade", type=_opt_float, default=d.f2f_along_fade,
                   help="with --f2f-along-sigma: keep its precision beyond the odometry's only where this scale "
                        "times the image's information on the forward translation falls short of it, or 'off' "
                        f"(default {_default(d.f2f_along_fade)})")
    p.add_argument("--f2f-along-distrust", type=_opt_count, default=d.f2f_along_distrust,
                   help="after a run of failed / rejected frame-to-frame links, keep this many accepted ones from the "
                        f"along-path prior, or 'off' (default {_default(d.f2f_along_distrust)})")
    p.add_argument("--f2f-fallback-window", type=_opt_count, default=d.f2f_fallback_window,
                   help="while more than --f2f-fallback-fail of the last this many frame-to-frame links failed, "
                        f"accepted links give the rotation only, or 'off' (default {_default(d.f2f_fallback_window)})")
    p.add_argument("--f2f-fallback-fail", type=float, default=d.f2f_fallback_fail,
                   help=f"the failed share of --f2f-fallback-window (default {_default(d.f2f_fallback_fail)})")
    p.add_argument("--f2f-along-check", type=_opt_float, default=d.f2f_along_check,
                   help="an accepted link whose along distance differs from the odometry's by more than this many "
                        f"odometry sigmas gives the rotation only, or 'off' (default {_default(d.f2f_along_check)})")
    p.add_argument("--f2f-loose-window", type=_opt_count, default=d.f2f_loose_window,
                   help="mark frames loose (MapperConfig.pose_lr_trans_loose) while more than --f2f-loose-fail of "
                        f"this many last links failed, or 'off' (default {_default(d.f2f_loose_window)}: "
                        "a frame whose own link failed or was rejected)")
    p.add_argument("--f2f-loose-fail", type=float, default=d.f2f_loose_fail,
                   help=f"the failed share of --f2f-loose-window (default {_default(d.f2f_loose_fail)})")
    p.add_argument("--f2f-loose-latch", action="store_true",
                   help="with --f2f-loose-window: once it has marked a frame, mark every later frame too")
    p.add_argument("--f2f-retry-depth-diff", type=_opt_float, default=d.f2f_retry_depth_diff,
                   help="retry a failed or rejected frame-to-frame step with this ICP depth limit in m "
                        f"or 'off' (default {_default(d.f2f_retry_depth_diff)})")
    p.add_argument("--odometry-seed", type=int, default=None,
                   help="seed of the simulator walk's odometry noise (default: the house seed, so each house "
                        "has its own noise sequence)")
    p.add_argument("--track-downscale", type=int, default=1, help="tracking image divisor (default 1)")
    p.add_argument("--rgbd-odometry", action="store_true", help="start tracking from OpenCV RGB-D odometry")
    p.add_argument("--planar", action="store_true", help="track planar motions only (ground robot)")
    p.add_argument("--pose-refine", action="store_true", help="refine tracked keyframe poses with the map")
    p.add_argument("--exposure", action=argparse.BooleanOptionalAction, default=None,
                   help="fit an affine colour per frame (default: on for TUM, a real auto-exposed camera; off "
                        "for the simulator)")
    p.add_argument("--runs", default=None, help="comma-separated subset of the runs (default: all)")
    p.add_argument("--iters", type=int, default=None, help="TUM mapping steps per frame (default 30)")
    p.add_argument("--first-iters", type=int, default=None, help="TUM mapping steps on the first frame (default 60)")
    p.add_argument("--refine", type=int, default=None, help="TUM refinement steps at the end (default 500)")
    p.add_argument("--mapper-set", action="append", default=[], metavar="FIELD=JSON",
                   help="set a MapperConfig field of the TUM and simulator settings, e.g. lambda_g=0.1 or "
                        "depth_edge_rel=0.05 (repeatable; for screening, recorded in results.jsonl)")
    p.add_argument("--data", default=TUM,
                   help="the TUM frames for tum / speed (default: ../shared/data/tum_fr1_xyz_first10 beside the "
                        "checkout; a worktree elsewhere names the shared folder here)")
    p.add_argument("--out", default="runs/slam_eval")
    a = p.parse_args(argv)
    if a.seed >= 1000 and not a.evaluation:
        p.error("seeds >= 1000 are evaluation houses, never tuned on: pass --evaluation for the held-out report")
    if a.evaluation and (a.what != "sim" or a.seed < 1000):
        p.error("--evaluation is for a simulator walk through an evaluation house (sim --seed >= 1000)")
    tcfg = TrackerConfig(iters=a.track_iters, downscale=a.track_downscale, rgbd_odometry=a.rgbd_odometry,
                         planar=a.planar, coarse_iters=a.track_coarse_iters, patience=a.track_patience,
                         prior_weight=a.prior_weight, prior_lateral_sigma=a.prior_lateral,
                         prior_rot_sigma=a.prior_rot_sigma, solver=a.track_solver, gn_iters=a.track_gn_iters,
                         prior_info_max=a.prior_info_max, gn_loss_tol=a.track_gn_loss_tol,
                         map_min_info=a.map_min_info, map_skip_max=a.map_skip_max, f2f_prior=a.f2f_prior,
                         f2f_rot_sigma=a.f2f_rot_sigma, f2f_max_depth_diff=a.f2f_max_depth_diff,
                         f2f_trans_sigma=a.f2f_trans_sigma, f2f_along_sigma=a.f2f_along_sigma,
                         f2f_retry_depth_diff=a.f2f_retry_depth_diff, jacobian=a.track_jacobian,
                         f2f_along_fade=a.f2f_along_fade, f2f_along_distrust=a.f2f_along_distrust,
                         f2f_fallback_window=a.f2f_fallback_window, f2f_fallback_fail=a.f2f_fallback_fail,
                         f2f_along_check=a.f2f_along_check, f2f_loose_window=a.f2f_loose_window,
                         f2f_loose_fail=a.f2f_loose_fail, f2f_loose_latch=a.f2f_loose_latch)
    try:
        tcfg.validate()
    except ValueError as e:
        p.error(str(e))
    for d in (REAL, SIM):
        d.update(pose_refine=a.pose_refine, pose_planar=a.planar)
        if a.exposure is not None:
            d["exposure"] = a.exposure
    global REAL_REFINE
    for item in a.mapper_set:
        key, _, val = item.partition("=")
        if key not in MapperConfig.__dataclass_fields__ or not val:
            p.error(f"--mapper-set {item!r}: expected FIELD=JSON with a MapperConfig field")
        try:
            val = json.loads(val)
        except json.JSONDecodeError:
            p.error(f"--mapper-set {item!r}: the value is not JSON")
        REAL[key] = SIM[key] = val
        _SET[key] = val
    for key, val in (("iters", a.iters), ("first_iters", a.first_iters)):
        if val is not None:
            REAL[key] = val
    if a.refine is not None:
        REAL_REFINE = a.refine
    want = None if a.runs is None else set(a.runs.split(","))
    go = lambda n: want is None or n in want  # noqa: E731
    if a.what in ("tum", "speed"):
        if not os.path.isdir(a.data):
            print(f"skipped: {a.data} not present", file=sys.stderr)
            return 1
        seq = datasets.load_sequence(a.data, downscale=a.downscale)
        if a.what == "speed":
            _run("tum_track_speed", seq, MapJob(MapperConfig(**REAL), tcfg, track=True, holdout_every=0), a.out)
            return 0
        if go("tum_gt"):
            _run("tum_gt", seq, MapJob(MapperConfig(**REAL), tcfg, holdout_every=0, refine=REAL_REFINE), a.out)
        if go("tum_track"):
            _run("tum_track", seq, MapJob(MapperConfig(**REAL), tcfg, track=True, holdout_every=0,
                                                     refine=REAL_REFINE), a.out)
        if go("tum_gt_refined"):  # tracking started from each ground-truth pose (pose refinement)
            _run("tum_gt_refined", seq, MapJob(MapperConfig(**REAL), tcfg, track=True, gt_prior=True, holdout_every=0,
                                               refine=REAL_REFINE), a.out)
        if go("tum_gt_holdout"):
            _run("tum_gt_holdout", seq, MapJob(MapperConfig(**REAL), tcfg, holdout_every=5, refine=REAL_REFINE), a.out)
    elif a.what == "frame-errors":
        seq = datasets.sim_walk(a.seed, a.frames, 320, 240, odometry_seed=a.seed)
        with open(os.path.join(a.out, "summary.json")) as f:
            summary = json.load(f)
        _, est = read_tum(os.path.join(a.out, "trajectory.txt"))
        done = [r["frame"] for r in summary["timing"]["per_frame"]]
        rows = frame_error_rows(summary, est, seq.gt_viewmats()[done])
        write_frame_errors(os.path.join(a.out, "frame_errors.tsv"), rows)
        print(f"{a.out}/frame_errors.tsv: {len(rows)} frames, ATE "
              f"{100 * np.sqrt(np.nanmean([r['error_cm'] ** 2 / 1e4 for r in rows])):.2f} cm")
    else:
        seq = datasets.sim_walk(a.seed, a.frames, 320, 240,
                                odometry_seed=a.seed if a.odometry_seed is None else a.odometry_seed)
        if go("sim_gt"):
            _run("sim_gt", seq, MapJob(MapperConfig(**SIM), tcfg, holdout_every=8), a.out)
        if go("sim_track"):
            _run("sim_track", seq, MapJob(MapperConfig(**SIM), tcfg, track=True, use_odometry=True, holdout_every=8),
                 a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
