"""The ``--track-*`` options of ``splatsearch map``: their argparse definitions and the
:class:`~splatsearch.slam.TrackerConfig` they make. Options left unset keep TrackerConfig's defaults,
and any of them set without ``--track`` is refused (they act on tracked poses only).

Building the parser must not import JAX (``splatsearch --help`` stays fast), so the defaults shown
in the help are :data:`DEFAULTS`, which a test keeps equal to TrackerConfig's."""

from __future__ import annotations

import argparse
from types import SimpleNamespace

from splatsearch.cli_types import positive_int

__all__ = ["DEFAULTS", "JACOBIANS", "SOLVERS", "add_track_args", "flags_needing_track", "tracker_config"]

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
    """The tracking options set in ``args`` (each is refused without ``--track``)."""
    return [flag for flag, on in (("--track-from-gt", args.track_from_gt),
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
