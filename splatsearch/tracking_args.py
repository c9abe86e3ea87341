"""The ``--track-*`` options of ``splatsearch map``: their argparse definitions and the
:class:`~splatsearch.slam.TrackerConfig` they make. Options left unset keep TrackerConfig's defaults,
and any of them set without ``--track`` is refused (they act on tracked poses only), as is any
``--tracker.FIELD`` override (every TrackerConfig field but ``planar``, added by
:mod:`splatsearch.cli_config` and applied after these options).

Building the parser must not import JAX (``splatsearch --help`` stays fast), so the defaults shown
in the help are :data:`DEFAULTS`, which a test keeps equal to TrackerConfig's."""

from __future__ import annotations

import argparse
from types import SimpleNamespace

from splatsearch.cli_types import positive_int

__all__ = ["DEFAULTS", "JACOBIANS", "SOLVERS", "TRACKER_FIELD_HELP", "add_track_args", "flags_needing_track",
           "map_tracker_config", "tracker_config"]

#: TrackerConfig's defaults of the fields these options set (tests/test_f2f_prior.py checks them).
DEFAULTS = dict(iters=40, solver="gn", gn_iters=10, gn_loss_tol=3e-3, coarse_iters=0, tol=1e-3, patience=0,
                prior_weight=1e-3, prior_lateral_sigma=0.01, f2f_prior=True, f2f_rot_sigma=1e-3, downscale=1,
                jacobian="analytic")
#: slam.SOLVERS
SOLVERS = ("adam", "gn")
#: slam.JACOBIANS
JACOBIANS = ("analytic", "finite-difference")


def _lateral(text: str) -> float | None:
    from splatsearch.slam import parse_lateral_sigma

    try:
        return parse_lateral_sigma(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _nonneg_float(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not x >= 0 or x == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite value >= 0, got {text}")
    return x


def _pos_float(text: str) -> float:
    x = _nonneg_float(text)
    if x <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return x


#: ``--tracker.FIELD`` help, one clause per TrackerConfig field (its docstring is prose, which
#: :func:`splatsearch.cli_config.field_help` cannot cut into per-field sentences);
#: tests/test_cli_config.py checks that every field but ``planar`` has one.
TRACKER_FIELD_HELP = {
    "iters": "solver adam: most Adam steps per frame at the tracking size",
    "lr_rot": "solver adam: step size of the rotation increment (rad)",
    "lr_trans": "solver adam: step size of the translation increment (m)",
    "lr_final": "solver adam: the step sizes decay to this fraction by a stage's last step (1: constant)",
    "coarse_iters": "solver adam: steps first on images coarse_downscale times smaller (0: no coarse stage)",
    "coarse_downscale": "how many times smaller the coarse stage's images are than the tracking size",
    "coarse_lr_scale": "the coarse stage's step sizes relative to lr_rot / lr_trans",
    "tol": "a stage stops once its best loss has not fallen by this fraction for patience steps",
    "patience": "steps without a tol improvement before a stage stops (0: always run every step)",
    "sil_thresh": "silhouette above which a pixel is trusted, in (0, 1)",
    "w_color": "weight of the colour L1 beside the depth L1 (SplaTAM: 0.5)",
    "outlier_k": "pixels whose depth error is above this x the median are left out (0: keep all)",
    "min_valid_frac": "fewer trusted pixels than this fraction of the image: the frame is not tracked",
    "diverge_ratio": "a last step's loss above this x the prediction's counts as divergence",
    "max_rot": "a correction beyond this (rad) counts as divergence; also rgbd_odometry's limit",
    "max_trans": "a correction beyond this (m) counts as divergence; also rgbd_odometry's limit",
    "submap_margin": "Gaussians projecting within this fraction of the image outside the view take part",
    "downscale": "track on images this many times smaller (area-averaged colour, subsampled depth)",
    "rgbd_odometry": "start each frame from OpenCV's RGB-D odometry between a map render and the frame",
    "prior_weight": "weight of the odometry prior against the image loss (with odometry only)",
    "prior_rot_sigma": "odometry prior's rotation sigma per frame (rad)",
    "prior_trans_sigma": "odometry prior's translation sigma as a fraction of the distance moved",
    "prior_trans_floor": "odometry prior's translation sigma added to prior_trans_sigma's (m)",
    "prior_lateral_sigma": "sigma across the direction of motion, a fraction of the distance (none: off)",
    "solver": "'gn' (Levenberg-Marquardt on reweighted L1) or 'adam' (SplaTAM's steps)",
    "gn_iters": "solver gn: most Levenberg-Marquardt steps per stage",
    "gn_fd_step": "solver gn, jacobian finite-difference: the difference step (rad / m)",
    "gn_eps_depth": "solver gn: IRLS weight floor of depth residuals (m)",
    "gn_eps_color": "solver gn: IRLS weight floor of colour residuals",
    "gn_step_tol": "solver gn: a step smaller than this ends the stage",
    "gn_eps_rel": "solver gn: IRLS floor as a multiple of the channel's mean |residual|",
    "gn_refresh": "solver gn: re-form the Jacobian after every accepted step (slower)",
    "gn_loss_tol": "solver gn: an accepted step lowering the loss by less than this fraction ends the stage",
    "jacobian": "solver gn: 'analytic' (one render) or 'finite-difference' (k renders)",
    "prior_info_max": "solver gn: most factor on the prior's rotation precision where the image fixes the "
                      "rotation less than the recent median (1: off)",
    "prior_info_window": "solver gn: tracked frames in that median",
    "map_min_info": "solver gn: frames whose rotation information is below this fraction of the median "
                    "are tracked but not mapped (0: off)",
    "map_skip_max": "most frames in a row that map_min_info leaves unmapped",
    "f2f_prior": "with odometry: OpenCV's frame-to-frame step, gated by the odometry, gives the rotation prior",
    "f2f_rot_sigma": "rotation sigma of an accepted frame-to-frame step (rad)",
    "f2f_max_depth_diff": "OpenCV's ICP correspondence limit for the frame-to-frame step (m)",
    "f2f_trans_sigma": "an accepted step's whole displacement with this sigma per axis (m; none: off)",
    "f2f_along_sigma": "an accepted step's distance along the path with this sigma (m; none: off)",
    "f2f_retry_depth_diff": "retry a failed or rejected step with this ICP limit (m; none: no retry)",
    "f2f_along_fade": "solver gn: fade the along-path prior where the image fixes the forward motion "
                      "(scale; none: off)",
    "f2f_along_distrust": "after 3+ links in a row not accepted, this many accepted links give the "
                          "rotation only (none: off)",
    "f2f_fallback_window": "links in the window of f2f_fallback_fail (none: off)",
    "f2f_fallback_fail": "while more than this share of the last f2f_fallback_window links failed, accepted "
                         "links give the rotation only",
    "f2f_along_check": "an accepted link whose along distance differs from the odometry's by more than this "
                       "many odometry sigmas gives the rotation only (none: off)",
    "f2f_loose_window": "mark frames loose (the mapper's pose_lr_trans_loose) while more than f2f_loose_fail of "
                        "this many last links failed (none: a frame whose own link failed or was rejected)",
    "f2f_loose_fail": "the failed share of f2f_loose_window",
    "f2f_loose_latch": "with f2f_loose_window: once it has marked a frame, every later frame is marked too",
}


def add_track_args(m: argparse.ArgumentParser) -> None:
    """Add the tracking options (all but ``--track`` itself) to the ``map`` subcommand's parser."""
    d = SimpleNamespace(**DEFAULTS)
    m.add_argument("--track-from-gt", action="store_true",
                   help="with --track: start each frame's tracking from its ground-truth pose (refines ground "
                        "truth that is not pixel-exact, e.g. TUM's motion capture)")
    m.add_argument("--track-iters", type=int, default=d.iters,
                   help="with --track-solver adam: most tracking Adam steps per frame at the tracking size, after "
                        f"the coarse ones (default {d.iters}; the fast setting: 8 with --track-coarse-iters 30 "
                        "--track-patience 5)")
    m.add_argument("--track-solver", choices=SOLVERS, default=None,
                   help="with --track: the pose solver: 'gn' (Levenberg-Marquardt on reweighted L1 residuals, "
                        f"at most --track-gn-iters steps; the default is {d.solver!r}) or 'adam' (SplaTAM's "
                        "first-order steps, --track-iters; 4-6x slower a frame)")
    m.add_argument("--track-gn-iters", type=positive_int, default=None,
                   help=f"with --track-solver gn: most Levenberg-Marquardt steps per frame (default {d.gn_iters})")
    m.add_argument("--track-jacobian", choices=JACOBIANS, default=None,
                   help="with --track-solver gn: how the pose Jacobian of the residuals is formed: 'analytic' (from "
                        "the one render at the pose: its colour and depth gradients through the pinhole projection "
                        "of its depth; saves 6 renders a frame, 3 with --track-planar) or 'finite-difference' (one "
                        f"extra render per pose parameter); default {d.jacobian!r}")
    m.add_argument("--track-gn-loss-tol", type=_nonneg_float, default=None,
                   help="with --track-solver gn: stop after an accepted step that lowers the loss by less than this "
                        f"fraction (0: never; default {d.gn_loss_tol:g})")
    m.add_argument("--track-coarse-iters", type=int, default=None,
                   help=f"most tracking Adam steps first on images 4x smaller still (0: none; default "
                        f"{d.coarse_iters})")
    m.add_argument("--track-patience", type=int, default=None,
                   help="a tracking stage stops once its loss has not fallen by a fraction "
                        f"{d.tol:g} for this many steps (0: run every step; default {d.patience})")
    m.add_argument("--track-prior-weight", type=float, default=None,
                   help="weight of the odometry prior in the tracking loss, per squared standard deviation of the "
                        f"odometry's noise (0: odometry is only the initial guess; default {d.prior_weight:g})")
    m.add_argument("--track-prior-lateral", type=_lateral, default=argparse.SUPPRESS, metavar="FRACTION|off",
                   help="odometry prior's standard deviation across the direction the odometry moved, as a "
                        f"fraction of the distance (a wheeled robot barely slips sideways; default "
                        f"{d.prior_lateral_sigma}), or 'off' for odometry that can slip sideways (then the same "
                        "as along it)")
    m.add_argument("--track-f2f-prior", action=argparse.BooleanOptionalAction, default=None,
                   help="with --track and odometry: take each frame's rotation from OpenCV's RGB-D odometry "
                        "against the previous raw frame where it agrees with the odometry within 3 sigma "
                        f"(default: {'on' if d.f2f_prior else 'off'})")
    m.add_argument("--track-f2f-rot-sigma", type=_pos_float, default=None, metavar="RAD",
                   help=f"rotation sigma of an accepted frame-to-frame step (default {d.f2f_rot_sigma:g} rad)")
    m.add_argument("--track-rgbd-odometry", action="store_true",
                   help="with --track: start each frame's tracking from OpenCV's RGB-D odometry between a "
                        "render of the map and the frame (one render, a few ms), then run --track-iters "
                        "Adam steps (default: off)")
    m.add_argument("--track-downscale", type=int, default=d.downscale,
                   help=f"track on images this many times smaller (faster; default {d.downscale})")
    m.add_argument("--track-planar", action="store_true",
                   help="with --track: a ground robot's camera (world z up): only horizontal translation and "
                        "turns about the vertical are estimated, so height, roll and pitch cannot drift "
                        "(default: off, full 6-DoF)")


def tracker_config(args: argparse.Namespace):
    """The :class:`~splatsearch.slam.TrackerConfig` of parsed ``map`` arguments (validated;
    ValueError on a bad combination)."""
    from splatsearch.slam import TrackerConfig

    tcfg = TrackerConfig(iters=args.track_iters, downscale=args.track_downscale,
                         rgbd_odometry=args.track_rgbd_odometry, planar=args.track_planar)
    for field, value in (("solver", args.track_solver), ("gn_iters", args.track_gn_iters),
                         ("gn_loss_tol", args.track_gn_loss_tol), ("jacobian", args.track_jacobian), ("coarse_iters", args.track_coarse_iters),
                         ("patience", args.track_patience), ("prior_weight", args.track_prior_weight),
                         ("f2f_prior", args.track_f2f_prior), ("f2f_rot_sigma", args.track_f2f_rot_sigma)):
        if value is not None:
            setattr(tcfg, field, value)
    if hasattr(args, "track_prior_lateral"):  # unset: absent (argparse.SUPPRESS), as "off" parses to None
        tcfg.prior_lateral_sigma = args.track_prior_lateral
    tcfg.validate()
    return tcfg


def flags_needing_track(args: argparse.Namespace) -> list[str]:
    """The tracking options set in ``args``: the ``--track-*`` flags and every ``--tracker.FIELD``
    override given (each is refused without ``--track``)."""
    overrides = [f"--{key}" for key in vars(args) if key.startswith("tracker.")]
    flags = [flag for flag, on in (("--track-from-gt", args.track_from_gt),
                                   ("--track-rgbd-odometry", args.track_rgbd_odometry),
                                   ("--track-planar", args.track_planar),
                                   ("--pose-refine", args.pose_refine),
                                   ("--track-coarse-iters", args.track_coarse_iters is not None),
                                   ("--track-solver", args.track_solver is not None),
                                   ("--track-gn-iters", args.track_gn_iters is not None),
                                   ("--track-gn-loss-tol", args.track_gn_loss_tol is not None),
                                   ("--track-jacobian", args.track_jacobian is not None),
                                   ("--track-patience", args.track_patience is not None),
                                   ("--track-prior-weight", args.track_prior_weight is not None),
                                   ("--track-prior-lateral", hasattr(args, "track_prior_lateral")),
                                   ("--track-f2f-prior", args.track_f2f_prior is not None),
                                   ("--track-f2f-rot-sigma", args.track_f2f_rot_sigma is not None)) if on]
    return flags + overrides


def map_tracker_config(args: argparse.Namespace):
    """The :class:`~splatsearch.slam.TrackerConfig` ``splatsearch map`` tracks with: the
    ``--track-*`` options, then the ``--tracker.FIELD`` overrides (which win), validated.
    ValueError naming the flags when any of them is given without ``--track``."""
    from splatsearch.cli_config import apply_overrides, config_overrides

    needs_track = flags_needing_track(args)
    if needs_track and not args.track:
        raise ValueError(f"{', '.join(needs_track)}: only with --track (these options act on tracked poses)")
    return apply_overrides(tracker_config(args), config_overrides(args, "tracker"))
