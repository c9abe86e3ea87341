"""Camera tracking against a Gaussian map, and the SLAM front end that tracks then maps.

Tracking (SplaTAM's, thesis Section 4.2.1 with poses unknown): with the map frozen, the pose of the
new frame is refined through the rasterizer's ``viewmat`` gradient, by Levenberg-Marquardt (the
default, :mod:`splatsearch.tracking_gn`) or by Adam (SplaTAM's; ``TrackerConfig.solver``). The loss
is L1 on depth plus ``w_color`` times L1 on colour over pixels the map covers (silhouette >
``sil_thresh``) with valid observed depth, leaving out pixels whose depth error exceeds
``outlier_k`` times the median (depth edges, moving things); those pixels are chosen once per stage,
at the pose the stage starts from. The pose update is a left-multiplied se(3) increment ``exp(xi) @
viewmat`` with xi = (rotation vector in rad, translation in m), both in the camera frame; Adam
scales each part by its own learning rate, so steps are well conditioned whatever the scene's size.
With the robot's odometry, a quadratic prior on xi (scaled by the odometry's noise over the frame)
joins the loss. An optional coarse stage on smaller images runs first; each stage is one jitted
``lax.while_loop`` that stops early once its loss stops falling, and the pose with the lowest loss
is kept.

A frame is not mapped (and its pose is the motion model's prediction) when its depth is all
invalid, its given pose is not finite, or tracking diverged: a non-finite loss, a last step's
loss above ``diverge_ratio`` times the prediction's, or a correction beyond ``max_rot`` /
``max_trans``. :class:`SLAM` reports each such frame in its :class:`FrameResult`.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, field

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import optax

from splatsearch import odometry_f2f
from splatsearch.gaussians import GaussianMap, render_args
from splatsearch.mapper import Mapper, MapperConfig, _bucket, _gather_rows
from splatsearch.precision import full_precision
from splatsearch.rasterization import rasterize
from splatsearch.rgbd import clean_depth
from splatsearch.tracking_gn import make_gn_stage


# --------------------------------------------------------------------------------------------
# se(3)
# --------------------------------------------------------------------------------------------

@full_precision
def so3_exp(w):
    """(3, 3) rotation of a rotation vector ``w`` (3,) in radians (Rodrigues, safe at 0)."""
    th2 = jnp.sum(w * w) + 1e-12
    th = jnp.sqrt(th2)
    k = jnp.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    a = jnp.where(th2 > 1e-8, jnp.sin(th) / th, 1.0 - th2 / 6)
    b = jnp.where(th2 > 1e-8, (1 - jnp.cos(th)) / th2, 0.5 - th2 / 24)
    return jnp.eye(3) + a * k + b * (k @ k)


@full_precision
def perturb_viewmat(viewmat, xi):
    """``T(xi) @ viewmat``: a world-to-camera matrix moved by xi = (rotation vector (rad),
    translation (m)), both expressed in the camera frame."""
    R = so3_exp(xi[:3])
    T = jnp.eye(4).at[:3, :3].set(R).at[:3, 3].set(xi[3:])
    return T @ viewmat


@full_precision
def planar_basis(viewmat: jax.Array) -> jax.Array:
    """(6, 3) basis, for the world-to-camera ``viewmat`` (4, 4), of the camera-frame se(3)
    increments (rotation vector in rad, translation in m) that move a camera in the world's
    horizontal plane (world z up): a turn about the vertical through the camera centre and the
    two horizontal translations. ``perturb_viewmat(viewmat, B @ p)`` keeps
    the camera's height, roll and pitch for any p (3,)."""
    R = viewmat[:3, :3]
    up = R[:, 2]  # world z in camera coordinates
    ex = R[:, 0] - up * jnp.dot(R[:, 0], up)  # world x, y in camera coordinates, kept normal to up
    ey = R[:, 1] - up * jnp.dot(R[:, 1], up)
    ex = ex / (jnp.linalg.norm(ex) + 1e-12)
    ey = ey - ex * jnp.dot(ex, ey)
    ey = ey / (jnp.linalg.norm(ey) + 1e-12)
    z3 = jnp.zeros(3, viewmat.dtype)
    cols = [jnp.concatenate([up, z3]), jnp.concatenate([z3, ex]), jnp.concatenate([z3, ey])]
    return jnp.stack(cols, axis=1)


def project_planar(viewmat: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """``viewmat`` (4, 4, world-to-camera) moved onto the planar motions of ``ref`` (4, 4), as
    float32 (4, 4): the camera-frame increment from ``ref`` is projected on :func:`planar_basis`
    (a ground robot cannot change its height, roll or pitch)."""
    ref = np.asarray(ref, np.float64)
    d = np.asarray(viewmat, np.float64) @ np.linalg.inv(ref)
    w = cv2.Rodrigues(d[:3, :3])[0].ravel()
    xi = np.concatenate([w, d[:3, 3]])
    B = np.asarray(planar_basis(jnp.asarray(ref, jnp.float32)), np.float64)
    return np.asarray(perturb_viewmat(jnp.asarray(ref, jnp.float32), jnp.asarray(B @ (B.T @ xi), jnp.float32)),
                      np.float32)


def pose_distance(vm_a, vm_b) -> tuple[float, float]:
    """(rotation angle in rad, camera-centre distance in m) between two world-to-camera poses."""
    a, b = np.asarray(vm_a, np.float64), np.asarray(vm_b, np.float64)
    ang = odometry_f2f.rotation_angle(a[:3, :3] @ b[:3, :3].T)
    return ang, float(np.linalg.norm(odometry_f2f.camera_displacement(a) - odometry_f2f.camera_displacement(b)))


# --------------------------------------------------------------------------------------------
# tracking
# --------------------------------------------------------------------------------------------


def diagonal_precision(weight: float, sigma_rot: float, sigma_trans: float) -> np.ndarray:
    """(6, 6) diagonal weight matrix ``weight / sigma^2`` of a pose prior on the se(3) increment
    (rotation vector rad: ``sigma_rot``; translation m: ``sigma_trans``)."""
    return np.diag([weight / sigma_rot ** 2] * 3 + [weight / sigma_trans ** 2] * 3)

#: tracking solvers: "adam" (first order, SplaTAM's) and "gn" (Levenberg-Marquardt on IRLS weights)
SOLVERS = ("adam", "gn")
#: Levenberg-Marquardt's Jacobian: from the one render at the pose (image gradients, pinhole, se(3))
#: or from k forward-difference renders
JACOBIANS = ("analytic", "finite-difference")
# f2f_along_distrust: links in a row not accepted before the next accepted ones are distrusted
F2F_DISTRUST_RUN = 3


@dataclass
class TrackerConfig:
    """Tracking settings.

    iters: most Adam steps per frame at the tracking resolution (``downscale``). coarse_iters:
    most Adam steps first on images ``coarse_downscale`` times smaller still (0: no coarse
    stage); a coarse step costs what its pixels cost, and it brings the pose near enough that a
    few full-size steps finish it (skipped when the coarse images would be under 32 pixels on
    a side). coarse_lr_scale: the coarse stage's step sizes relative to
    ``lr_rot`` / ``lr_trans``. tol, patience: a stage stops early once its best loss has not
    fallen by a fraction ``tol`` for ``patience`` steps (patience 0: always run every step).
    lr_rot (rad), lr_trans (m): Adam step sizes of the se(3) increment. lr_final: the step sizes
    decay exponentially to this fraction of themselves by a stage's last step (1: constant).
    sil_thresh: silhouette above which a pixel is trusted. w_color: weight of the colour L1
    (SplaTAM: 0.5). outlier_k: pixels with depth error above ``outlier_k`` x median are left out
    (0: keep all). The trusted pixels are chosen once per stage, at the pose the stage starts
    from, so every step of a stage minimises the same objective (a mask re-chosen at every step
    lets the pose lower the loss by pushing hard pixels out of it). min_valid_frac: fewer trusted
    pixels than this fraction of the image means the map does not cover the view: tracking is
    skipped. diverge_ratio, max_rot (rad), max_trans (m): divergence tests (see the module
    docstring). submap_margin: Gaussians whose means project within this fraction of the image
    outside the view take part. downscale: track on images this many times smaller
    (area-averaged colour, subsampled depth): the rasterizer's cost falls with the pixel count.
    rgbd_odometry: before the Adam steps, align a render of the map at the initial pose to the
    frame with OpenCV's multi-scale RGB-D odometry (``cv2.Odometry``: ICP + photometric, else
    photometric alone) and start from its pose when it succeeds within ``max_rot`` /
    ``max_trans``. planar: a ground robot's camera moves in the world's horizontal plane and
    turns about the world's vertical axis (world z up): the update is restricted to those 3
    degrees of freedom, so height, roll and pitch keep the initial guess's values.

    solver: "gn" (default): Levenberg-Marquardt on the same loss and trusted pixels, at most
    ``gn_iters`` steps per stage; or "adam" (the steps above, ``iters`` of them, SplaTAM's).
    Levenberg-Marquardt's metric is the Gauss-Newton matrix of the L1 terms reweighted as in IRLS:
    the residuals' Jacobian w.r.t. the k pose parameters from k forward-difference renders (step
    ``gn_fd_step`` rad / m), each pixel and channel weighted by 1 / max(|r|, eps) with eps the
    larger of ``gn_eps_depth`` (m) / ``gn_eps_color`` and ``gn_eps_rel`` x the channel's mean |r| (a
    floor that keeps nearly exact pixels from dominating the metric). jacobian: "analytic" (default
    since stop 44: from the one render at the pose the metric is formed at, the render's colour and
    depth gradients chained with the pinhole projection of its back-projected depth and the se(3)
    generators, plus the depth's own z motion; :func:`splatsearch.tracking_gn.analytic_jacobian`;
    saves k renders a stage) or "finite-difference" (the k renders above; on very small images,
    e.g. the tests' 96x72, its metric converges in fewer steps). gn_refresh False (default):
    the metric is formed once at the stage's start and each step then costs one forward + pose-only
    backward for the exact gradient; True: Jacobian and gradient are re-formed from k + 1 renders
    after every accepted step. A step that does not lower the loss is rejected and the damping
    raised; a stage ends after ``gn_iters`` steps, a step below ``gn_step_tol``, an accepted step
    that lowers the loss by less than a fraction ``gn_loss_tol`` (0: never), or damping past 1e6.

    Odometry prior (used when :func:`track` gets ``prior_sigma``, which :class:`SLAM` passes when
    the robot's odometry is given): the loss adds ``prior_weight`` x (|w| / sigma_rot)^2 + (|t| /
    sigma_trans)^2 for the increment (w rad, t m) from the odometry's prediction, with sigma_rot =
    ``prior_rot_sigma`` rad and sigma_trans = ``prior_trans_sigma`` x the distance the odometry
    moved + ``prior_trans_floor`` m (the odometry's noise per frame). Odometry and the image then
    both count: on flat, weakly textured walls the image alone barely fixes a sideways shift, and a
    shift there trades against a turn. ``prior_lateral_sigma`` (a fraction of the distance, None:
    off) gives the translation across the odometry's direction of motion its own, tighter sigma (a
    wheeled robot's odometry errs along its path, hardly sideways; default 0.01); see
    :meth:`prior_precision`. Set it to None for odometry that can slip sideways. prior_info_max (>
    1, "gn" only): where the image fixes the rotation less than it did on earlier frames
    (:attr:`TrackResult.rot_info` below the median of the last ``prior_info_window`` tracked
    frames'), the prior's rotation precision is multiplied by that shortfall, at most
    ``prior_info_max`` (1: off). Along a plain wall the image barely separates a turn from a
    sideways shift, and the map's small errors then choose the heading. map_min_info (in [0, 1),
    "gn" only; 0: off): :class:`SLAM` tracks but does not map a frame whose ``rot_info`` is below
    this fraction of that median (its pose is poorly fixed, and what it would add to the map would
    carry its heading error into later frames), at most ``map_skip_max`` frames in a row.

    Frame-to-frame rotation prior (``f2f_prior``, default on; acts only when :class:`SLAM` gets the
    robot's odometry): OpenCV's RGB-D odometry between the previous raw frame and the current one
    (:mod:`splatsearch.odometry_f2f`, through frames given to :meth:`SLAM.observe` too), accepted
    when its rotation and displacement agree with the wheel odometry's step within 3 sigma of the
    prior above (planar: its yaw only). An accepted rotation replaces the wheel odometry's in the
    prediction, and the prior's rotation sigma becomes ``f2f_rot_sigma`` rad. f2f_max_depth_diff
    (m): OpenCV's ICP correspondence limit (see :func:`~splatsearch.odometry_f2f.f2f_step`).
    f2f_trans_sigma (m, None: off): an accepted step's camera displacement replaces the wheel
    odometry's too (planar: its horizontal part), with this sigma on each axis. f2f_along_sigma
    (m, default 1e-3 since stop 46, None: off; unused when f2f_trans_sigma is set): only the
    displacement's component along the
    wheel odometry's direction of motion is taken from an accepted step, with this sigma along that
    direction; across it the wheel odometry's prediction and ``prior_lateral_sigma`` stay
    (:func:`~splatsearch.odometry_f2f.along_step`; the odometry errs in distance travelled). With
    ``MapperConfig.pose_refine`` the mapper's keyframe pose refinement has no such prior and at
    its default translation step (2e-4 m) moves frames back along the path toward the map's drift;
    the simulator recipe pairs these defaults with ``pose_lr_trans`` 2e-5 (results.md, stop 46).
    f2f_retry_depth_diff (m, default 0.15 since stop 46, None: off): a step that OpenCV fails or
    the gate rejects at
    ``f2f_max_depth_diff`` is tried once more with this ICP correspondence limit (OpenCV starts from
    no motion, so in a turn or a long step most pairs lie beyond 0.07 m; the retry is gated the same
    way). f2f_along_fade (> 0, None: off; with ``f2f_along_sigma``, "gn" only): the along-path
    precision beyond the wheel odometry's own (prior_weight x (1 / f2f_along_sigma^2 - 1 / the
    odometry's along sigma^2)) is kept only in the fraction
    :func:`~splatsearch.tracking_gn.fade_weight` of ``f2f_along_fade`` x the image's information on
    the translation along the path (:attr:`TrackResult.fwd_info`, measured at the prediction with
    the rest of the pose free): the tight along-path prior then acts where the map render barely
    fixes the forward motion (a corridor seen along its axis) and fades where the image pins it,
    so the heading need not absorb a mismatch the translation is held from taking. The scale
    calibrates the start pose's information (its IRLS metric, which grows as the loss falls)
    against the prior's curvature. f2f_along_distrust (int >= 1, default 2 since stop 46's rule J, None: off): after
    a run of at least ``F2F_DISTRUST_RUN`` links in a row that OpenCV failed or the gate rejected,
    the next this many accepted links give the rotation prior only, not the along-path one (where
    OpenCV fails often its accepted steps are also less reliable: on dev houses 4 and 25, 8-16 mm
    errors that pass the gate, three of four right after such a run). f2f_fallback_window (int >= 1,
    None: off) and f2f_fallback_fail (in [0, 1)): while more than ``f2f_fallback_fail`` of the last
    ``f2f_fallback_window`` links (raw frame to raw frame, held-out frames included; links not yet
    made count as not failed) were failed by OpenCV, accepted links give the rotation prior only, as
    stop 44's tracking did (where OpenCV fails this often its accepted distances are not trusted).
    f2f_along_check (k > 0, None: off): an accepted link whose OpenCV distance along the wheel
    odometry's direction of motion differs from the odometry's own by more than k x the odometry
    prior's translation sigma for that link (:meth:`prior_sigma`) gives the rotation prior only (the
    gate allows 3 sigma on the whole displacement; this asks the along part alone to agree better).
    f2f_loose_window (int >= 1, None: off) and f2f_loose_fail (in [0, 1)): which processed frames
    are marked ``loose`` for :class:`~splatsearch.mapper.Mapper` (whose
    ``MapperConfig.pose_lr_trans_loose``, when set, is then their keyframe refinement's translation
    step): off, a frame whose own frame-to-frame link failed or was rejected; set, instead, every
    frame processed while more than ``f2f_loose_fail`` of the last ``f2f_loose_window`` links
    (raw frames, held-out ones included; links not yet made count as not failed) were failed by
    OpenCV, whatever its own link (a stretch of walk where OpenCV fails often, and the heading the
    tracker carries out of it has drifted: dev house 170 at stop 48). f2f_loose_latch (with
    f2f_loose_window): once that window has marked a frame, every later frame is marked too.
    """

    iters: int = 40
    lr_rot: float = 2e-3
    lr_trans: float = 2e-3
    lr_final: float = 1.0
    coarse_iters: int = 0
    coarse_downscale: int = 4
    coarse_lr_scale: float = 1.0
    tol: float = 1e-3
    patience: int = 0
    sil_thresh: float = 0.99
    w_color: float = 0.5
    outlier_k: float = 10.0
    min_valid_frac: float = 0.02
    diverge_ratio: float = 2.0
    max_rot: float = 0.35
    max_trans: float = 0.5
    submap_margin: float = 0.25
    downscale: int = 1
    rgbd_odometry: bool = False
    planar: bool = False
    prior_weight: float = 1e-3
    prior_rot_sigma: float = 0.01
    prior_trans_sigma: float = 0.05
    prior_trans_floor: float = 1e-3
    prior_lateral_sigma: float | None = 0.01
    solver: str = "gn"
    gn_iters: int = 10
    gn_fd_step: float = 1e-3
    gn_eps_depth: float = 1e-3
    gn_eps_color: float = 1e-2
    gn_step_tol: float = 1e-5
    gn_eps_rel: float = 2.0
    gn_refresh: bool = False
    gn_loss_tol: float = 3e-3
    jacobian: str = "analytic"
    prior_info_max: float = 1.0
    prior_info_window: int = 20
    map_min_info: float = 0.0
    map_skip_max: int = 5
    f2f_prior: bool = True
    f2f_rot_sigma: float = 1e-3
    f2f_max_depth_diff: float = 0.07
    f2f_trans_sigma: float | None = None
    f2f_along_sigma: float | None = 1e-3
    f2f_retry_depth_diff: float | None = 0.15
    f2f_along_fade: float | None = None
    f2f_along_distrust: int | None = 2
    f2f_fallback_window: int | None = None
    f2f_fallback_fail: float = 0.35
    f2f_along_check: float | None = None
    f2f_loose_window: int | None = None
    f2f_loose_fail: float = 0.25
    f2f_loose_latch: bool = False

    def validate(self) -> None:
        if not (self.f2f_rot_sigma > 0 and math.isfinite(self.f2f_rot_sigma)):
            raise ValueError(f"f2f_rot_sigma must be a finite value > 0, got {self.f2f_rot_sigma}")
        if self.f2f_trans_sigma is not None and not (self.f2f_trans_sigma > 0 and math.isfinite(self.f2f_trans_sigma)):
            raise ValueError(f"f2f_trans_sigma must be None or a finite value > 0, got {self.f2f_trans_sigma}")
        if self.f2f_along_sigma is not None and not (self.f2f_along_sigma > 0 and math.isfinite(self.f2f_along_sigma)):
            raise ValueError(f"f2f_along_sigma must be None or a finite value > 0, got {self.f2f_along_sigma}")
        if self.f2f_retry_depth_diff is not None and not (self.f2f_retry_depth_diff > 0
                                                          and math.isfinite(self.f2f_retry_depth_diff)):
            raise ValueError(f"f2f_retry_depth_diff must be None or a finite value > 0, got {self.f2f_retry_depth_diff}")
        if self.f2f_along_fade is not None and not (self.f2f_along_fade > 0 and math.isfinite(self.f2f_along_fade)):
            raise ValueError(f"f2f_along_fade must be None or a finite value > 0, got {self.f2f_along_fade}")
        if self.f2f_along_distrust is not None and not self.f2f_along_distrust >= 1:
            raise ValueError(f"f2f_along_distrust must be None or >= 1, got {self.f2f_along_distrust}")
        if self.f2f_fallback_window is not None and not self.f2f_fallback_window >= 1:
            raise ValueError(f"f2f_fallback_window must be None or >= 1, got {self.f2f_fallback_window}")
        if not 0 <= self.f2f_fallback_fail < 1:
            raise ValueError(f"f2f_fallback_fail must be in [0, 1), got {self.f2f_fallback_fail}")
        if self.f2f_loose_window is not None and not self.f2f_loose_window >= 1:
            raise ValueError(f"f2f_loose_window must be None or >= 1, got {self.f2f_loose_window}")
        if not 0 <= self.f2f_loose_fail < 1:
            raise ValueError(f"f2f_loose_fail must be in [0, 1), got {self.f2f_loose_fail}")
        if self.f2f_along_check is not None and not (self.f2f_along_check > 0 and math.isfinite(self.f2f_along_check)):
            raise ValueError(f"f2f_along_check must be None or a finite value > 0, got {self.f2f_along_check}")
        if not (self.f2f_max_depth_diff > 0 and math.isfinite(self.f2f_max_depth_diff)):
            raise ValueError(f"f2f_max_depth_diff must be a finite value > 0, got {self.f2f_max_depth_diff}")
        if self.jacobian not in JACOBIANS:
            raise ValueError(f"jacobian must be one of {JACOBIANS}, got {self.jacobian!r}")
        if self.solver not in SOLVERS:
            raise ValueError(f"solver must be one of {SOLVERS}, got {self.solver!r}")
        if self.gn_iters < 1 or not (self.gn_fd_step > 0 and self.gn_eps_depth > 0 and self.gn_eps_color > 0
                                     and self.gn_step_tol >= 0 and self.gn_eps_rel >= 0):
            raise ValueError("gn_iters >= 1, gn_fd_step > 0, gn_eps_depth > 0, gn_eps_color > 0, "
                             "gn_eps_rel >= 0 and gn_step_tol >= 0 are required")
        if not (self.prior_info_max >= 1 and math.isfinite(self.prior_info_max)):
            raise ValueError(f"prior_info_max must be a finite value >= 1, got {self.prior_info_max}")
        if not self.gn_loss_tol >= 0:
            raise ValueError(f"gn_loss_tol must be >= 0, got {self.gn_loss_tol}")
        if not (0 <= self.map_min_info < 1) or self.map_skip_max < 0:
            raise ValueError("map_min_info in [0, 1) and map_skip_max >= 0 are required")
        if self.prior_info_window < 1:
            raise ValueError(f"prior_info_window must be >= 1, got {self.prior_info_window}")
        if self.iters < 1:
            raise ValueError(f"tracking iters must be >= 1, got {self.iters}")
        if self.coarse_iters < 0 or self.coarse_downscale < 1 or self.patience < 0 or self.tol < 0:
            raise ValueError("coarse_iters >= 0, coarse_downscale >= 1, patience >= 0 and tol >= 0 are required")
        if not (self.lr_rot > 0 and self.lr_trans > 0 and self.coarse_lr_scale > 0):
            raise ValueError("lr_rot, lr_trans and coarse_lr_scale must be > 0")
        if not 0 < self.lr_final <= 1:
            raise ValueError(f"lr_final must be in (0, 1], got {self.lr_final}")
        if self.downscale < 1:
            raise ValueError(f"downscale must be >= 1, got {self.downscale}")
        if not 0 < self.sil_thresh < 1:
            raise ValueError(f"sil_thresh must be in (0, 1), got {self.sil_thresh}")
        if not (self.prior_weight >= 0 and math.isfinite(self.prior_weight)) or not (self.prior_rot_sigma > 0 and self.prior_trans_sigma >= 0
                                         and self.prior_trans_floor > 0):
            raise ValueError("a finite prior_weight >= 0, prior_rot_sigma > 0, prior_trans_sigma >= 0 and "
                             "prior_trans_floor > 0 are required")
        if self.prior_lateral_sigma is not None and not (self.prior_lateral_sigma >= 0
                                                         and math.isfinite(self.prior_lateral_sigma)):
            raise ValueError(f"prior_lateral_sigma must be None or a finite value >= 0, got {self.prior_lateral_sigma}")

    def prior_sigma(self, odometry_step) -> tuple[float, float]:
        """(sigma_rot rad, sigma_trans m) of the odometry prior for an odometry motion
        ``odometry_step`` (4, 4) between two frames."""
        dist = float(np.linalg.norm(np.asarray(odometry_step, np.float64)[:3, 3]))
        return self.prior_rot_sigma, self.prior_trans_sigma * dist + self.prior_trans_floor

    def prior_precision(self, odometry_step) -> np.ndarray:
        """(6, 6) weight matrix Q (prior_weight included) of the odometry prior xi^T Q xi on the
        camera-frame increment xi (rotation vector rad, translation m) for an odometry motion
        ``odometry_step`` (4, 4, world-to-camera of the new frame times camera-to-world of the
        previous). Along the direction moved the translation's sigma is :meth:`prior_sigma`'s;
        across it, ``prior_lateral_sigma`` x the distance + ``prior_trans_floor`` (None: the same
        as along it)."""
        step = np.asarray(odometry_step, np.float64)
        sr, st = self.prior_sigma(step)
        Q = diagonal_precision(self.prior_weight, sr, st)
        if self.prior_lateral_sigma is not None and float(np.linalg.norm(step[:3, 3])) > 0:
            # the motion's axis in the new camera frame
            Q[3:, 3:] = self.axis_precision(step[:3, 3], st, self.lateral_sigma(step))
        return Q

    def lateral_sigma(self, odometry_step) -> float:
        """Sigma (m) of the odometry prior's translation across the direction moved by
        ``odometry_step`` (4, 4): ``prior_lateral_sigma`` x the distance + ``prior_trans_floor``,
        or (``prior_lateral_sigma`` None) :meth:`prior_sigma`'s translation sigma."""
        if self.prior_lateral_sigma is None:
            return self.prior_sigma(odometry_step)[1]
        dist = float(np.linalg.norm(np.asarray(odometry_step, np.float64)[:3, 3]))
        return self.prior_lateral_sigma * dist + self.prior_trans_floor

    def axis_precision(self, axis: np.ndarray, s_along: float, s_across: float) -> np.ndarray:
        """(3, 3) translation weight (prior_weight included) with sigma ``s_along`` (m) along
        ``axis`` (3,) (any length > 0, camera frame) and ``s_across`` (m) across it."""
        d = np.asarray(axis, np.float64) / np.linalg.norm(axis)
        P = np.outer(d, d)
        return self.prior_weight * (P / s_along ** 2 + (np.eye(3) - P) / s_across ** 2)


def parse_lateral_sigma(text: str) -> float | None:
    """``prior_lateral_sigma`` from a command-line value: a fraction of the distance moved (>= 0),
    or "off" (None: the sideways sigma is the same as along the motion). Raises ValueError."""
    if text.strip().lower() in ("off", "none"):
        return None
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"the lateral prior takes a fraction >= 0 or 'off', got {text!r}") from None
    if not (value >= 0 and math.isfinite(value)):
        raise ValueError(f"the lateral prior takes a fraction >= 0 or 'off', got {text!r}")
    return value


@dataclass
class TrackResult:
    """viewmat (4, 4) refined world-to-camera; loss (final best, at the tracking resolution) and
    loss0 (the same loss where the Adam steps start: the initial pose, or the RGB-D odometry's);
    valid_frac: trusted pixel fraction at the initial pose; status "ok", "diverged" or
    "no_overlap"; steps: solver steps run (all stages; Adam steps, or Levenberg-Marquardt
    steps including rejected ones); rot_info ("gn" only, else NaN): the image's information on
    the rotation with the translation free, at the start pose, per image pixel and independent
    of the residuals' size (the Schur complement of the data metric's translation block, times
    the data loss, times the trusted fraction); fwd_info ("gn" with a ``fade_axis``, else NaN):
    the image's information on the translation along that axis with the other pose directions
    free, at the start pose, in the data loss's curvature units (comparable with twice a prior
    precision, m^-2; :func:`~splatsearch.tracking_gn.axis_information`); fade: the fraction of
    ``prior_fade`` kept (:func:`~splatsearch.tracking_gn.fade_weight`; 0 without one); seconds:
    wall time; cpu_seconds: process CPU time (all threads), which on a shared machine shows the
    cost better than the wall time."""

    viewmat: np.ndarray
    loss: float
    loss0: float
    valid_frac: float
    status: str
    seconds: float
    cpu_seconds: float = 0.0
    steps: int = 0
    rot_info: float = float("nan")
    fwd_info: float = float("nan")
    fade: float = 0.0


_TRACK_FNS: dict = {}
#: the tracker's rasterizer backward: the map is frozen, so only the pose gradient is formed
_TRACK_DIFF = "viewmat"


def trusted_pixels(alpha: jax.Array, d_err: jax.Array, depth: jax.Array, sil_thresh: float,
                   outlier_k: float) -> jax.Array:
    """The pixels tracking trusts, (H, W) float32 in {0, 1}: rendered silhouette ``alpha`` (H, W)
    above ``sil_thresh``, valid observed ``depth`` (H, W, m), and (``outlier_k`` > 0) a depth error
    ``d_err`` = |rendered - observed| (H, W, m) at most ``outlier_k`` x its median over the covered
    pixels (depth edges, things that moved). The one definition for the tracker's stages and
    :func:`pose_jacobian`, so the diagnostics see the tracker's pixels."""
    m = (alpha > sil_thresh) & (depth > 0)
    if outlier_k > 0:
        med = jnp.nanmedian(jnp.where(m, d_err, jnp.nan))
        m = m & (d_err <= outlier_k * jnp.where(jnp.isfinite(med), med, jnp.inf))
    return m.astype(jnp.float32)


def _track_fn(levels: tuple, cfg: TrackerConfig):
    """Jitted tracker over ``levels``: ((K bytes, W, H, max steps, lr scale), ...), coarse first."""
    key = (levels, cfg.lr_rot, cfg.lr_trans, cfg.sil_thresh, cfg.w_color, cfg.outlier_k, cfg.planar, cfg.lr_final,
           cfg.tol, cfg.patience, cfg.solver, cfg.gn_fd_step, cfg.gn_eps_depth, cfg.gn_eps_color, cfg.gn_step_tol,
           cfg.gn_eps_rel, cfg.gn_refresh, cfg.prior_info_max, cfg.gn_loss_tol, cfg.jacobian)
    if key in _TRACK_FNS:
        return _TRACK_FNS[key]
    planar = cfg.planar
    lrs = jnp.array([cfg.lr_rot] + [cfg.lr_trans] * 2 if planar else [cfg.lr_rot] * 3 + [cfg.lr_trans] * 3,
                    jnp.float32)
    adam = optax.adam(1.0)  # unit steps, scaled per component by ``lrs``
    sil, w_c, ok_k = cfg.sil_thresh, cfg.w_color, cfg.outlier_k
    tol, patience = cfg.tol, cfg.patience

    def make_level(Kb, W, H):
        Kj = jnp.asarray(np.frombuffer(Kb, np.float32).reshape(3, 3))

        def render(xi, margs, vm_ref):
            return rasterize(*margs, perturb_viewmat(vm_ref, xi), Kj, W, H, render_mode="RGB+D", validate=False,
                             differentiable=_TRACK_DIFF)

        def mask_at(xi, margs, depth, vm_ref, out=None):
            """The trusted pixels (H, W) float at the increment xi: covered, valid depth, no outlier
            (``out``: the render at xi when already made)."""
            out = render(xi, margs, vm_ref) if out is None else out
            return trusted_pixels(out.alpha[..., 0], jnp.abs(out.depth[..., 0] - depth), depth, sil, ok_k)

        def loss(p, margs, rgb, depth, vm_ref, basis, mf, pw):
            xi = basis @ p
            out = render(xi, margs, vm_ref)
            n = jnp.maximum(mf.sum(), 1.0)
            d_err = jnp.abs(out.depth[..., 0] - depth)
            c_err = jnp.abs(out.image - rgb).sum(-1)
            return (jnp.sum(d_err * mf) + w_c * jnp.sum(c_err * mf)) / n + xi @ pw @ xi

        def residual(p, margs, rgb, depth, vm_ref, basis, with_mask=False):
            """(H, W, 4) rendered minus observed (depth m, then colour) at p; with ``with_mask``
            also the trusted pixels there (one render for both)."""
            out = render(basis @ p, margs, vm_ref)
            r = jnp.concatenate([out.depth - depth[..., None], out.image - rgb], -1)
            return (r, mask_at(None, margs, depth, vm_ref, out)) if with_mask else r

        return mask_at, loss, jax.value_and_grad(loss), residual, Kj

    fns = [make_level(Kb, W, H) for Kb, W, H, _, _ in levels]
    gn_stage = make_gn_stage(cfg)

    def stage(p, n_steps, lr_scale, fn, margs, rgb, depth, vm_ref, basis, pw, info_ref, fade):
        """Adam steps from p on one level; returns (best p, its loss, steps run, ...). The faded prior
        (``fade``) is a Levenberg-Marquardt feature: Adam leaves it out (weight 0)."""
        mask_at, loss, vg, *_ = fn
        mf = mask_at(basis @ p, margs, depth, vm_ref)
        decay = jnp.log(jnp.float32(cfg.lr_final)) / max(n_steps - 1, 1)

        def cond(c):
            k, _, _, _, _, stall = c
            go = k < n_steps
            return go & (stall < patience) if patience > 0 else go

        def body(c):
            k, p, st, best_p, best_loss, stall = c
            val, g = vg(p, margs, rgb, depth, vm_ref, basis, mf, pw)
            progress = val < best_loss * (1.0 - tol)
            better = val < best_loss  # NaN compares False: a NaN step is never kept
            best_p = jnp.where(better, p, best_p)
            best_loss = jnp.where(better, val, best_loss)
            stall = jnp.where(progress, 0, stall + 1)
            g = jnp.where(jnp.isfinite(g), g, 0.0)
            upd, st = adam.update(g, st)
            p = p + upd * lrs * lr_scale * jnp.exp(decay * k.astype(jnp.float32))
            return k + 1, p, st, best_p, best_loss, stall

        c = (jnp.int32(0), p, adam.init(p), p, jnp.asarray(jnp.inf, jnp.float32), jnp.int32(0))
        k, p_last, _, best_p, best_loss, _ = jax.lax.while_loop(cond, body, c)
        last = loss(p_last, margs, rgb, depth, vm_ref, basis, mf, pw)  # the last update is not scored yet
        better = last < best_loss
        return (jnp.where(better, p_last, best_p), jnp.where(better, last, best_loss), k, mf, last,
                jnp.float32(jnp.nan), jnp.float32(jnp.nan), jnp.float32(jnp.nan), jnp.float32(0.0))

    @jax.jit
    @full_precision
    def run(margs, images, vm_ref, xi_start, pw, info_ref, fade):
        basis = planar_basis(vm_ref) if planar else jnp.eye(6, dtype=jnp.float32)
        p0 = basis.T @ xi_start  # the basis is orthonormal
        p, steps, frac0 = p0, jnp.int32(0), None
        for (rgb, depth), fn, (_, _, _, n_steps, lr_scale) in zip(images, fns, levels):
            p, best_loss, k, mf, last, info, start, fwd_info, wf = (gn_stage if cfg.solver == "gn" else stage)(
                p, n_steps, lr_scale, fn, margs, rgb, depth, vm_ref, basis, pw, info_ref, fade)
            frac0 = mf.mean() if frac0 is None else frac0  # the first stage's pixels are chosen at p0
            steps = steps + k
        rgb, depth = images[-1]
        if len(levels) == 1 and cfg.solver == "gn" and cfg.prior_info_max <= 1:
            loss0 = start  # the stage's own loss at p0 on its pixels: no extra render
        else:
            # on the last stage's pixels, with the faded prior's share that stage kept
            loss0 = fns[-1][1](p0, margs, rgb, depth, vm_ref, basis, mf, pw + wf * fade[0])
        return perturb_viewmat(vm_ref, basis @ p), best_loss, loss0, frac0, steps, last, info, fwd_info, wf

    if len(_TRACK_FNS) > 8:
        _TRACK_FNS.pop(next(iter(_TRACK_FNS)))
    _TRACK_FNS[key] = run
    return run


def pose_jacobian(gmap: GaussianMap, rgb: np.ndarray, depth: np.ndarray, viewmat: np.ndarray, K: np.ndarray,
                  width: int, height: int, method: str = "analytic", config: TrackerConfig | None = None,
                  basis: np.ndarray | None = None, order: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tracker's residuals at ``viewmat`` and their Jacobian w.r.t. the pose, as the
    Levenberg-Marquardt stage forms it (for tests and diagnostics; the tracker forms its own
    inside its jitted loop).

    Args:
        gmap: the map (all active Gaussians are rendered). rgb (H, W, 3), depth (H, W) m: the frame.
        viewmat (4, 4), K (3, 3), width, height: the camera.
        method: "analytic" (:func:`splatsearch.tracking_gn.analytic_jacobian`), "finite-difference"
            (forward differences, step ``config.gn_fd_step``) or "central" (central differences of
            the same step, a reference).
        config: supplies sil_thresh, outlier_k, gn_fd_step. basis: (6, k) (default: identity).
        order: the analytic Jacobian's image derivative (2: central differences, 4: five-point).

    Returns:
        (J (H, W, 4, k), residual (H, W, 4) rendered minus observed (depth, colour), trusted
        pixel mask (H, W) float), numpy float32.
    """
    from splatsearch.tracking_gn import analytic_jacobian

    cfg = config or TrackerConfig()
    Kj = jnp.asarray(np.asarray(K, np.float32))
    vm = jnp.asarray(np.asarray(viewmat, np.float32))
    basis = jnp.eye(6, dtype=jnp.float32) if basis is None else jnp.asarray(basis, jnp.float32)
    margs = render_args(gmap.params(), gmap.active, gmap.isotropic)
    rgb, depth = jnp.asarray(rgb, jnp.float32), jnp.asarray(depth, jnp.float32)

    @jax.jit
    @full_precision
    def residual(p):
        out = rasterize(*margs, perturb_viewmat(vm, basis @ p), Kj, width, height, render_mode="RGB+D",
                        validate=False)
        return jnp.concatenate([out.depth - depth[..., None], out.image - rgb], -1), out.alpha[..., 0]

    k = basis.shape[1]
    r, alpha = residual(jnp.zeros(k, jnp.float32))
    m = trusted_pixels(alpha, jnp.abs(r[..., 0]), depth, cfg.sil_thresh, cfg.outlier_k)
    h = cfg.gn_fd_step
    if method == "analytic":
        J = jax.jit(full_precision(analytic_jacobian), static_argnums=5)(r, rgb, depth, Kj, basis, order)
    elif method == "finite-difference":
        J = jnp.stack([(residual(h * jnp.eye(k)[j])[0] - r) / h for j in range(k)], -1)
    elif method == "central":
        J = jnp.stack([(residual(h * jnp.eye(k)[j])[0] - residual(-h * jnp.eye(k)[j])[0]) / (2 * h)
                       for j in range(k)], -1)
    else:
        raise ValueError(f"method must be 'analytic', 'finite-difference' or 'central', got {method!r}")
    return np.asarray(J, np.float32), np.asarray(r, np.float32), np.asarray(m, np.float32)


def _shrink(rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, s: int):
    """(rgb, depth, K, W, H) of a frame ``s`` times smaller: area-averaged colour, subsampled
    depth (averaging would invent depths across edges)."""
    H, W = depth.shape
    w, h = W // s, H // s
    if s == 1:
        return rgb, depth, K, W, H
    K = K.copy()
    K[:2] /= s
    return (cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA),
            np.ascontiguousarray(depth[s // 2::s, s // 2::s][:h, :w]), K, w, h)


def visible_rows(gmap: GaussianMap, viewmat, K, W: int, H: int, margin: float) -> np.ndarray:
    """Rows of active Gaussians whose means project inside the view grown by ``margin``."""
    n = gmap.n_active
    means = np.asarray(gmap.means)[:n]
    vm = np.asarray(viewmat, np.float32)
    pc = means @ vm[:3, :3].T + vm[:3, 3]
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * pc[:, 0] / z + K[0, 2]
        v = K[1, 1] * pc[:, 1] / z + K[1, 2]
    vis = (z > 0.01) & (u > -margin * W) & (u < (1 + margin) * W) & (v > -margin * H) & (v < (1 + margin) * H)
    return np.nonzero(vis)[0]


def odometry_init(margs, rgb, depth, viewmat, K, width: int, height: int, sil_thresh: float = 0.9,
                  max_rot: float = 0.35, max_trans: float = 0.5) -> np.ndarray | None:
    """Pose of an RGB-D frame from OpenCV's RGB-D odometry between a render of the map at
    ``viewmat`` and the frame (rgb (H, W, 3) [0, 1], depth (H, W) m). Returns the refined
    world-to-camera (4, 4), or None when OpenCV fails or moves the pose beyond ``max_rot`` (rad)
    / ``max_trans`` (m). Only pixels the map covers (alpha > ``sil_thresh``) take part."""
    out = rasterize(*margs, jnp.asarray(viewmat, jnp.float32), jnp.asarray(K, jnp.float32), width, height,
                    render_mode="RGB+D", validate=False)
    r_depth = np.array(out.depth[..., 0], np.float32)
    r_depth[np.asarray(out.alpha[..., 0]) < sil_thresh] = 0.0
    gray = lambda im: cv2.cvtColor((np.clip(np.asarray(im), 0, 1) * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
    settings = cv2.OdometrySettings()
    settings.setCameraMatrix(np.asarray(K, np.float32))
    # ICP + photometric first; photometric alone where ICP has too little geometry (a flat wall)
    for kind in (cv2.OdometryType_RGB_DEPTH, cv2.OdometryType_RGB):
        odo = cv2.Odometry(kind, settings, cv2.OdometryAlgoType_COMMON)
        src = cv2.OdometryFrame(depth=r_depth, image=gray(out.image))
        dst = cv2.OdometryFrame(depth=np.ascontiguousarray(depth, np.float32), image=gray(rgb))
        try:
            odo.prepareFrames(src, dst)
            ok, Rt = odo.compute(src, dst)
        except cv2.error:
            continue
        if not ok or Rt is None or not np.all(np.isfinite(Rt)):
            continue
        vm = (np.asarray(Rt, np.float64) @ np.asarray(viewmat, np.float64)).astype(np.float32)  # render -> frame
        ang, dist = pose_distance(vm, viewmat)
        if ang <= max_rot and dist <= max_trans:
            return vm
    return None


def track(gmap: GaussianMap, rgb, depth, init_viewmat, K, width: int, height: int,
          config: TrackerConfig | None = None, *, prior_sigma: tuple[float, float] | None = None,
          prior_precision: np.ndarray | None = None, info_ref: float | None = None,
          prior_fade: np.ndarray | None = None, fade_axis: np.ndarray | None = None, fade_scale: float = 1.0,
          **overrides) -> TrackResult:
    """Refine the world-to-camera pose of an RGB-D frame against a frozen map.

    Args:
        gmap: the map. rgb (H, W, 3) [0, 1]; depth (H, W) metres, 0 = invalid.
        init_viewmat: (4, 4) initial guess (constant velocity, odometry, ...).
        K: (3, 3) intrinsics; width, height: image size.
        config: :class:`TrackerConfig`; keyword ``overrides`` replace its fields (e.g. iters=80).
        prior_sigma: (rad, m) standard deviations of ``init_viewmat`` as a prediction (the
            odometry's noise over this frame, see :meth:`TrackerConfig.prior_sigma`): the loss
            then keeps the pose near it, weighted by ``config.prior_weight``. None: no prior.
        prior_precision: (6, 6) weight matrix Q of the prior term xi^T Q xi on the increment xi
            (rotation vector rad, translation m) from ``init_viewmat``, already including
            ``prior_weight`` (see :meth:`TrackerConfig.prior_precision`); replaces ``prior_sigma``.
        info_ref: with the "gn" solver and ``config.prior_info_max`` > 1, the image's usual
            rotation information (:attr:`TrackResult.rot_info` of earlier frames; None or 0: the
            prior is used as given). A frame whose ``rot_info`` is below it has the prior's
            rotation precision raised by ``info_ref / rot_info``, at most ``prior_info_max``.
        fade_axis: (3,) a translation direction in the camera frame (any length; e.g. the
            odometry's direction of motion): the "gn" solver measures the image's information on
            it (:attr:`TrackResult.fwd_info`). prior_fade: (6, 6) an extra prior precision on xi
            (prior_weight included) added to the prior in the fraction
            :func:`~splatsearch.tracking_gn.fade_weight` of ``fade_scale`` x that information
            (``fade_axis`` required; "gn" only, Adam leaves it out).

    Returns:
        :class:`TrackResult`; on divergence or without overlap its viewmat is ``init_viewmat``.
    """
    cfg = config or TrackerConfig()
    if overrides:
        cfg = TrackerConfig(**{**cfg.__dict__, **overrides})
    cfg.validate()
    t0, c0 = time.perf_counter(), time.process_time()
    K = np.asarray(K, np.float32)
    vm0 = np.asarray(init_viewmat, np.float32)
    if not np.all(np.isfinite(vm0)):
        raise ValueError("init_viewmat contains NaN or Inf")
    rows = visible_rows(gmap, vm0, K, width, height, cfg.submap_margin) if gmap.n_active else np.zeros(0, int)
    rgb = np.asarray(rgb, np.float32)
    depth = np.asarray(depth, np.float32)
    if rgb.shape != (height, width, 3) or depth.shape != (height, width):
        raise ValueError(f"expected rgb ({height}, {width}, 3) and depth ({height}, {width}), got {rgb.shape}, "
                         f"{depth.shape}")
    if len(rows) == 0:
        return TrackResult(vm0, float("nan"), float("nan"), 0.0, "no_overlap", time.perf_counter() - t0,
                           time.process_time() - c0)
    rgb, depth, K, width, height = _shrink(rgb, depth, K, cfg.downscale)
    stages = []  # (rgb, depth, K, W, H, steps, lr scale), coarse first
    s = cfg.coarse_downscale
    if cfg.coarse_iters > 0 and s > 1 and min(width, height) // s >= 32:  # smaller: too few pixels to steer
        stages.append((*_shrink(rgb, depth, K, s), cfg.coarse_iters, cfg.coarse_lr_scale))
    stages.append((rgb, depth, K, width, height, cfg.gn_iters if cfg.solver == "gn" else cfg.iters, 1.0))
    if _bucket(len(rows)) < gmap.capacity:
        params, active, _, _ = _gather_rows(gmap, None, rows)
    else:
        params, active = gmap.params(), gmap.active
    margs = render_args(params, active, gmap.isotropic)
    xi_start = np.zeros(6, np.float32)
    if cfg.rgbd_odometry:
        vm_odo = odometry_init(margs, rgb, depth, vm0, K, int(width), int(height), max_rot=cfg.max_rot,
                               max_trans=cfg.max_trans)
        if vm_odo is not None:
            d = np.asarray(vm_odo, np.float64) @ np.linalg.inv(vm0.astype(np.float64))
            xi_start = np.concatenate([cv2.Rodrigues(d[:3, :3])[0].ravel(), d[:3, 3]]).astype(np.float32)
    pw = np.zeros((6, 6), np.float32)  # prior precision on xi (already scaled by prior_weight)
    if prior_precision is not None:
        pw = np.asarray(prior_precision, np.float32)
        if pw.shape != (6, 6) or not np.all(np.isfinite(pw)):
            raise ValueError(f"prior_precision must be a finite (6, 6) matrix, got shape {pw.shape}")
    elif prior_sigma is not None and cfg.prior_weight > 0:
        pw = diagonal_precision(cfg.prior_weight, *prior_sigma).astype(np.float32)
    if not (fade_scale > 0 and math.isfinite(fade_scale)):
        raise ValueError(f"fade_scale must be a finite value > 0, got {fade_scale}")
    pf, axis6 = np.zeros((6, 6), np.float32), np.zeros(6, np.float32)
    if fade_axis is not None:
        ax = np.asarray(fade_axis, np.float64).reshape(3)
        if not (np.all(np.isfinite(ax)) and np.linalg.norm(ax) > 0):
            raise ValueError(f"fade_axis must be a finite non-zero (3,) vector, got {fade_axis}")
        axis6[3:] = ax / np.linalg.norm(ax)
    if prior_fade is not None:
        if fade_axis is None:
            raise ValueError("prior_fade needs fade_axis (the direction whose information fades it)")
        pf = np.asarray(prior_fade, np.float32)
        if pf.shape != (6, 6) or not np.all(np.isfinite(pf)):
            raise ValueError(f"prior_fade must be a finite (6, 6) matrix, got shape {pf.shape}")
    levels = tuple((np.asarray(k, np.float32).tobytes(), int(w), int(h), int(n), float(lr))
                   for _, _, k, w, h, n, lr in stages)
    images = tuple((jnp.asarray(r, jnp.float32), jnp.asarray(d, jnp.float32)) for r, d, *_ in stages)
    run = _track_fn(levels, cfg)
    vm, loss, loss0, frac0, steps, last, info, fwd_info, wf = run(
        margs, images, jnp.asarray(vm0), jnp.asarray(xi_start), jnp.asarray(pw), jnp.float32(info_ref or 0.0),
        (jnp.asarray(pf), jnp.asarray(axis6), jnp.float32(fade_scale)))
    vm, loss, loss0, frac0, last = np.asarray(vm), float(loss), float(loss0), float(frac0), float(last)
    status = "ok"
    if frac0 < cfg.min_valid_frac:
        status, vm = "no_overlap", vm0
    # the best pose is never worse than the start, but steps that ran away (the last one's loss
    # far above the start's, or not finite) mean the optimisation cannot be trusted
    elif not (np.isfinite(loss) and np.isfinite(last) and np.all(np.isfinite(vm))) or \
            max(loss, last) > cfg.diverge_ratio * loss0:
        status, vm = "diverged", vm0
    else:
        ang, dist = pose_distance(vm, vm0)
        if ang > cfg.max_rot or dist > cfg.max_trans:
            status, vm = "diverged", vm0
    return TrackResult(vm.astype(np.float32), loss, loss0, frac0, status, time.perf_counter() - t0,
                       time.process_time() - c0, int(steps), float(info),
                       float(fwd_info) if fade_axis is not None else float("nan"), float(wf))


# --------------------------------------------------------------------------------------------
# SLAM front end
# --------------------------------------------------------------------------------------------

@dataclass
class FrameResult:
    """What :meth:`SLAM.process` did with one frame.

    viewmat: the frame's pose estimate (world-to-camera); status: "mapped", "first",
    "skipped_no_depth" (too little valid depth), "skipped_bad_rgb" (NaN/Inf colour),
    "skipped_bad_pose" (a given pose that is not finite), "tracked" (tracked, not mapped: the image
    fixed its rotation too weakly, ``TrackerConfig.map_min_info``) or "skipped_tracking" (diverged: the
    pose is the prediction, the frame is not mapped); track: the :class:`TrackResult` when
    tracked; t_track, t_map: seconds; stats: the mapper's update stats when mapped; f2f: what the
    frame-to-frame rotation prior did ("accepted", "rejected": OpenCV disagreed with the wheel
    odometry, "failed": OpenCV found no motion, None: not tried).
    """

    index: int
    viewmat: np.ndarray
    status: str
    track: TrackResult | None = None
    t_track: float = 0.0
    t_map: float = 0.0
    stats: dict = field(default_factory=dict)
    f2f: str | None = None

    @property
    def mapped(self) -> bool:
        return self.status in ("mapped", "first")


class SLAM:
    """Track-then-map front end over :class:`~splatsearch.mapper.Mapper`.

    Each frame's pose is predicted (a given pose, the robot's odometry motion applied to the last
    estimate, or constant velocity), refined by :func:`track` against the current map unless
    ``track=False``, then the frame is mapped at that pose.

    Args:
        K (3, 3), width, height: the camera.
        mapper_config, tracker_config: settings.
        track: refine poses through the map (False: trust the given poses, as ground truth).
        min_valid_depth: a frame with fewer valid depth pixels than this fraction is skipped.
    """

    def __init__(self, K, width: int, height: int, mapper_config: MapperConfig | None = None,
                 tracker_config: TrackerConfig | None = None, *, track: bool = True,
                 min_valid_depth: float = 0.01):
        self.mapper = Mapper(K, width, height, mapper_config)
        self.tcfg = tracker_config or TrackerConfig()
        self.tcfg.validate()
        self.track_enabled = bool(track)
        self.min_valid_depth = float(min_valid_depth)
        self.poses: list[np.ndarray] = []  # estimate per processed frame
        self.results: list[FrameResult] = []
        self._last_odom: np.ndarray | None = None
        self._rot_info: list[float] = []  # TrackResult.rot_info of the frames tracked "ok"
        self._unmapped = 0  # frames in a row tracked but not mapped (map_min_info)
        # frame-to-frame chain: the last raw frame seen (processed or observed), its odometry, and
        # the OpenCV motion accumulated since the last processed frame (None: a link failed)
        self._f2f_ref: tuple[np.ndarray, np.ndarray] | None = None
        self._f2f_ref_odom: np.ndarray | None = None
        self._f2f_acc: np.ndarray | None = np.eye(4)
        self._f2f_link: str | None = None  # the worst link status since the last processed frame
        self._f2f_status: str | None = None  # this frame's, for its FrameResult
        self._f2f_bad_run = 0  # links in a row not accepted (f2f_along_distrust)
        self._f2f_distrust_left = 0  # accepted links still to be kept from the along prior
        self._f2f_untrusted = False  # a link of the current chain was
        self._f2f_recent: deque[bool] = deque(maxlen=self.tcfg.f2f_fallback_window or 1)  # last links failed?
        self._f2f_recent_loose: deque[bool] = deque(maxlen=self.tcfg.f2f_loose_window or 1)  # the same, loose window
        self._loose_latched = False  # f2f_loose_latch: the loose window has fired once

    @property
    def K(self):
        return self.mapper.K

    def predict(self, odometry=None) -> np.ndarray:
        """Initial pose guess for the next frame: odometry motion since the previous frame applied
        to the last estimate when ``odometry`` (the odometry's world-to-camera) is given and the
        previous frame had one, else constant velocity, else the last pose, else identity."""
        good = [p for p in self.poses if np.all(np.isfinite(p))]
        if not good:
            return np.eye(4, dtype=np.float32)
        last = good[-1].astype(np.float64)
        if odometry is not None and self._last_odom is not None:
            # world-to-camera: vm_k = (vm_k^odom inv(vm_{k-1}^odom)) vm_{k-1}
            rel = np.asarray(odometry, np.float64) @ np.linalg.inv(self._last_odom)
            return (rel @ last).astype(np.float32)
        if len(good) >= 2:
            rel = last @ np.linalg.inv(good[-2].astype(np.float64))
            return (rel @ last).astype(np.float32)
        return last.astype(np.float32)

    def process(self, rgb, depth, viewmat=None, *, odometry=None, prior=None) -> FrameResult:
        """Track (unless disabled) and map one RGB-D frame.

        Args:
            rgb (H, W, 3) [0, 1]; depth (H, W) metres, 0 = invalid.
            viewmat: the frame's given pose: with ``track=False`` it is used as is; with tracking,
                only the first frame's is used (its map frame), later ones are ignored.
            odometry: optional (4, 4) world-to-camera pose from odometry (any drifting frame: only
                its motion between frames is used) as the tracking prior.
            prior: optional (4, 4) absolute initial guess for tracking (e.g. a ground-truth pose
                to be refined); it replaces the prediction.
        """
        i = len(self.poses)
        rgb = np.asarray(rgb, np.float32)
        depth = np.nan_to_num(np.asarray(depth, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        first = not any(r.mapped for r in self.results)
        pred = self.predict(odometry)
        # the odometry's motion since the last frame: how far the prediction can be trusted
        prior_q = rel_odo = prior_fade = fade_axis = None
        if odometry is not None and self._last_odom is not None and np.all(np.isfinite(odometry)) \
                and self.tcfg.prior_weight > 0:
            rel_odo = np.asarray(odometry, np.float64) @ np.linalg.inv(self._last_odom)
            prior_q = self.tcfg.prior_precision(rel_odo)
            if np.linalg.norm(rel_odo[:3, 3]) > 1e-3:  # the image's information along the motion is logged
                fade_axis = rel_odo[:3, 3]
        f2f_status = None
        if prior_q is not None and prior is None and self.track_enabled and not first and self.tcfg.f2f_prior:
            self._f2f_link_to(rgb, depth, odometry)
            f2f_status = self._f2f_link
            if self._f2f_acc is not None and self._f2f_link == "accepted":
                last = [p for p in self.poses if np.all(np.isfinite(p))][-1].astype(np.float64)
                prior_q = prior_q.copy()
                prior_q[:3, :3] = np.eye(3) * (self.tcfg.prior_weight / self.tcfg.f2f_rot_sigma ** 2)
                if self.tcfg.f2f_trans_sigma is None and self.tcfg.f2f_along_sigma is not None \
                        and not self._f2f_untrusted and np.linalg.norm(rel_odo[:3, 3]) > 1e-3:
                    # OpenCV's distance along the odometry's direction of motion, the odometry's across it
                    step = odometry_f2f.along_step(rel_odo, self._f2f_acc)
                    s_along, s_odo = self.tcfg.f2f_along_sigma, self.tcfg.prior_sigma(rel_odo)[1]
                    if self.tcfg.f2f_along_fade is not None and s_along < s_odo:
                        # the odometry's own along sigma always; the rest only where the image lacks it
                        fade_axis = step[:3, 3]
                        prior_q[3:, 3:] = self.tcfg.axis_precision(fade_axis, s_odo, self.tcfg.lateral_sigma(rel_odo))
                        d = fade_axis / np.linalg.norm(fade_axis)
                        prior_fade = np.zeros((6, 6))
                        prior_fade[3:, 3:] = self.tcfg.prior_weight * (1 / s_along ** 2 - 1 / s_odo ** 2) * np.outer(d, d)
                    else:
                        prior_q[3:, 3:] = self.tcfg.axis_precision(step[:3, 3], s_along, self.tcfg.lateral_sigma(rel_odo))
                elif self.tcfg.f2f_trans_sigma is None:
                    step = odometry_f2f.prior_step(rel_odo, self._f2f_acc)
                else:  # OpenCV's displacement too
                    step = self._f2f_acc
                    if self.tcfg.planar:
                        step = odometry_f2f.horizontal_step(step, self._last_odom[:3, 2])
                    prior_q[3:, 3:] = np.eye(3) * (self.tcfg.prior_weight / self.tcfg.f2f_trans_sigma ** 2)
                pred = (step @ last).astype(np.float32)
        self._f2f_reset(rgb, depth, odometry)
        self._f2f_status = f2f_status
        if prior is not None and np.all(np.isfinite(prior)):
            pred, prior_q, prior_fade = np.asarray(prior, np.float32), None, None
        if odometry is not None and np.all(np.isfinite(odometry)):
            self._last_odom = np.asarray(odometry, np.float64)
        res: FrameResult
        given_ok = viewmat is not None and np.all(np.isfinite(viewmat))
        if not self.track_enabled or (first and viewmat is not None):
            if not given_ok:
                res = FrameResult(i, pred if self.track_enabled else np.full((4, 4), np.nan, np.float32),
                                  "skipped_bad_pose")
                return self._finish(res)
            pose = np.asarray(viewmat, np.float32)
        else:
            pose = pred
        c = self.mapper.cfg
        if c.min_depth > 0 or np.isfinite(c.max_depth) or c.depth_edge_rel > 0:
            depth = clean_depth(depth, c.min_depth, c.max_depth, c.depth_edge_rel)
        if rgb.shape != (self.mapper.H, self.mapper.W, 3) or depth.shape != (self.mapper.H, self.mapper.W):
            raise ValueError(f"expected rgb ({self.mapper.H}, {self.mapper.W}, 3) and depth ({self.mapper.H}, "
                             f"{self.mapper.W}), got {rgb.shape}, {depth.shape}")
        if not np.all(np.isfinite(rgb)):
            return self._finish(FrameResult(i, pose, "skipped_bad_rgb"))
        if np.mean(depth > 0) < self.min_valid_depth:
            return self._finish(FrameResult(i, pose, "skipped_no_depth"))
        tr = None
        t_track = 0.0
        if self.track_enabled and not first:
            recent = self._rot_info[-self.tcfg.prior_info_window:]
            info_ref = float(np.median(recent)) if len(recent) >= 3 else None
            tr = track(self.mapper.map, rgb, depth, pose, self.K, self.mapper.W, self.mapper.H, self.tcfg,
                       prior_precision=prior_q, info_ref=info_ref, prior_fade=prior_fade, fade_axis=fade_axis,
                       fade_scale=self.tcfg.f2f_along_fade or 1.0)
            t_track = tr.seconds
            if tr.status == "ok" and np.isfinite(tr.rot_info):
                self._rot_info.append(tr.rot_info)
                weak = info_ref is not None and tr.rot_info < self.tcfg.map_min_info * info_ref
                if weak and self._unmapped < self.tcfg.map_skip_max:
                    self._unmapped += 1
                    return self._finish(FrameResult(i, tr.viewmat, "tracked", tr, t_track))
            self._unmapped = 0
            if tr.status == "diverged":
                return self._finish(FrameResult(i, pose, "skipped_tracking", tr, t_track))
            pose = tr.viewmat
        t0 = time.perf_counter()
        # a frame whose frame-to-frame step failed or was rejected had no along-path anchor
        # (or, with f2f_loose_window, one in a stretch where OpenCV fails often):
        # MapperConfig.pose_lr_trans_loose (when set) lets the map pull it further
        stats = self.mapper.update(rgb, depth, pose, refine_pose=self.track_enabled and not first, tag=i,
                                   loose=self._loose())
        self._apply_refined(stats.pop("poses", {}))
        pose = np.asarray(stats.pop("viewmat", pose), np.float32)
        return self._finish(FrameResult(i, pose, "first" if first else "mapped", tr, t_track,
                                        time.perf_counter() - t0, stats))

    def _apply_refined(self, poses: dict) -> None:
        """Write poses refined by the mapper (``MapperConfig.pose_refine``) into the trajectory."""
        for tag, vm in poses.items():
            if 0 <= tag < len(self.poses) and np.all(np.isfinite(vm)):
                self.poses[tag] = np.asarray(vm, np.float32)
                self.results[tag].viewmat = self.poses[tag]

    def refine(self, iters: int) -> float:
        """``Mapper.refine`` over the keyframes; poses it refines go into the trajectory."""
        loss = self.mapper.refine(iters)
        self._apply_refined({f.tag: f.viewmat for f in self.mapper.keyframes if f.tag is not None and f.refine_pose})
        return loss

    def localize(self, rgb, depth, init_viewmat) -> np.ndarray:
        """Pose (4, 4) of a frame tracked against the current map from ``init_viewmat`` (no prior,
        nothing mapped): how a held-out view is placed in the map's own frame for evaluation.
        rgb (H, W, 3) [0, 1]; depth (H, W) m. Returns ``init_viewmat`` when tracking fails."""
        depth = np.nan_to_num(np.asarray(depth, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        c = self.mapper.cfg
        if c.min_depth > 0 or np.isfinite(c.max_depth) or c.depth_edge_rel > 0:
            depth = clean_depth(depth, c.min_depth, c.max_depth, c.depth_edge_rel)
        tr = track(self.mapper.map, np.asarray(rgb, np.float32), depth, init_viewmat, self.K, self.mapper.W,
                   self.mapper.H, self.tcfg)
        return np.asarray(tr.viewmat if tr.status == "ok" else init_viewmat, np.float32)

    def observe(self, rgb, depth, odometry=None) -> str | None:
        """Show the tracker a frame that is neither tracked nor mapped (a held-out view): with
        ``TrackerConfig.f2f_prior`` and ``odometry`` (4, 4), it becomes the next frame-to-frame
        reference, so the chain of raw frames has no gap. rgb (H, W, 3) [0, 1]; depth (H, W) m.
        Returns the link's status ("accepted", "rejected", "failed") or None when not tried."""
        if not (self.track_enabled and self.tcfg.f2f_prior and odometry is not None
                and np.all(np.isfinite(odometry)) and self._f2f_ref is not None):
            return None
        rgb = np.asarray(rgb, np.float32)
        depth = np.nan_to_num(np.asarray(depth, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        status = self._f2f_link_to(rgb, depth, odometry)
        if np.all(np.isfinite(rgb)):
            self._f2f_ref, self._f2f_ref_odom = (rgb, depth), np.asarray(odometry, np.float64)
        return status

    def _f2f_link_to(self, rgb: np.ndarray, depth: np.ndarray, odometry) -> str | None:
        """Add the OpenCV step from the reference frame to this one to the chain; its status."""
        if self._f2f_ref is None or self._f2f_ref_odom is None or odometry is None:
            self._f2f_acc, self._f2f_link = None, "failed"
            return "failed"
        odo = np.asarray(odometry, np.float64) @ np.linalg.inv(self._f2f_ref_odom)
        sr, st = self.tcfg.prior_sigma(odo)
        limits = [self.tcfg.f2f_max_depth_diff] + ([self.tcfg.f2f_retry_depth_diff]
                                                   if self.tcfg.f2f_retry_depth_diff is not None else [])
        for md in limits:
            step = odometry_f2f.f2f_step(*self._f2f_ref, rgb, depth, self.K, max_depth_diff=md)
            if step is not None and self.tcfg.planar:
                step = odometry_f2f.planar_yaw_only(step, self._f2f_ref_odom[:3, 2])
            status = "failed" if step is None else ("accepted" if odometry_f2f.gate_step(step, odo, sr, st)
                                                    else "rejected")
            if status == "accepted":
                break
        self._f2f_recent.append(status == "failed")
        self._f2f_recent_loose.append(status == "failed")
        if status == "accepted":
            if self._f2f_fallback() or self._f2f_along_disagrees(step, odo, st):
                self._f2f_untrusted = True
            if self.tcfg.f2f_along_distrust and self._f2f_bad_run >= F2F_DISTRUST_RUN:
                self._f2f_distrust_left = self.tcfg.f2f_along_distrust
            if self._f2f_distrust_left > 0:
                self._f2f_distrust_left -= 1
                self._f2f_untrusted = True
            self._f2f_bad_run = 0
        else:
            self._f2f_bad_run += 1
        if status != "accepted" or self._f2f_acc is None:
            self._f2f_acc = None
        else:
            self._f2f_acc = step @ self._f2f_acc
        rank = {None: 0, "accepted": 1, "rejected": 2, "failed": 3}
        if rank[status] > rank[self._f2f_link]:
            self._f2f_link = status
        return status

    def _f2f_along_disagrees(self, step: np.ndarray, odo: np.ndarray, sigma_trans: float) -> bool:
        """Whether an accepted link's OpenCV step ``step`` (4, 4) moves along the odometry's direction
        of motion (``odo`` (4, 4), the link's odometry step) by more than ``f2f_along_check`` x
        ``sigma_trans`` (m) away from the odometry's distance (never when off or not moving)."""
        k = self.tcfg.f2f_along_check
        if k is None:
            return False
        d_odo = odometry_f2f.camera_displacement(odo)
        dist = float(np.linalg.norm(d_odo))
        if dist < 1e-3:
            return False
        return abs(float((odometry_f2f.camera_displacement(step) - d_odo) @ d_odo) / dist) > k * sigma_trans

    def _loose(self) -> bool:
        """Whether the frame being mapped is marked loose (see ``TrackerConfig.f2f_loose_window``)."""
        k = self.tcfg.f2f_loose_window
        if k is None:
            return self._f2f_status in ("failed", "rejected")
        fired = sum(self._f2f_recent_loose) > self.tcfg.f2f_loose_fail * k
        if fired and self.tcfg.f2f_loose_latch:
            self._loose_latched = True
        return fired or self._loose_latched

    def _f2f_fallback(self) -> bool:
        """Whether OpenCV failed on more than ``f2f_fallback_fail`` of the last
        ``f2f_fallback_window`` links (this one included; links not yet made count as not failed)."""
        k = self.tcfg.f2f_fallback_window
        return k is not None and sum(self._f2f_recent) > self.tcfg.f2f_fallback_fail * k

    def _f2f_reset(self, rgb: np.ndarray, depth: np.ndarray, odometry) -> None:
        """A processed frame starts a new chain."""
        ok = odometry is not None and np.all(np.isfinite(odometry)) and np.all(np.isfinite(rgb))
        self._f2f_ref = (rgb, depth) if ok and self.tcfg.f2f_prior else None
        self._f2f_ref_odom = np.asarray(odometry, np.float64) if ok else None
        self._f2f_acc, self._f2f_link = np.eye(4), None
        self._f2f_untrusted = False

    def _finish(self, res: FrameResult) -> FrameResult:
        res.f2f, self._f2f_status = self._f2f_status, None
        self.poses.append(np.asarray(res.viewmat, np.float32))
        self.results.append(res)
        return res

    def trajectory(self) -> np.ndarray:
        """(N, 4, 4) estimated world-to-camera poses of every processed frame."""
        return np.stack(self.poses) if self.poses else np.zeros((0, 4, 4), np.float32)
