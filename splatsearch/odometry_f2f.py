"""Frame-to-frame rotation prior for tracking: OpenCV RGB-D odometry between consecutive raw frames.

The map render at the predicted pose fixes a robot's heading poorly where much of the view lies
beyond the depth range or along a plain wall; the previous raw frame, seen a few centimetres
earlier, fixes the rotation between the two frames directly. :func:`f2f_step` estimates that
relative motion with ``cv2.Odometry``; :func:`gate_step` accepts it only where it agrees with the
wheel odometry's step (the wheel odometry is then a sanity check on OpenCV, and OpenCV refines
the wheel odometry's rotation, which is its noisiest part); :func:`prior_step` builds the
tracker's prediction and prior precision from the accepted rotation.

All steps are world-to-camera relative transforms ``vm_k @ inv(vm_{k-1})`` (4, 4): a point in
the previous camera frame maps to the current one.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["camera_displacement", "f2f_step", "gate_step", "horizontal_step", "planar_yaw_only", "prior_step", "along_step",
           "rotation_angle"]


def _gray(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor((np.clip(np.asarray(rgb, np.float32), 0, 1) * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)


def f2f_step(prev_rgb: np.ndarray, prev_depth: np.ndarray, rgb: np.ndarray, depth: np.ndarray, K,
             *, max_depth: float = 10.0, max_translation: float = 0.3, max_rotation_deg: float = 15.0,
             max_depth_diff: float = 0.07, kind: str = "rgbd") -> np.ndarray | None:
    """Relative motion between two raw RGB-D frames from OpenCV's RGB-D odometry.

    Args:
        prev_rgb, rgb: (H, W, 3) float [0, 1]; prev_depth, depth: (H, W) metres, 0 = invalid.
        K: (3, 3) intrinsics.
        max_depth: pixels farther than this (m) are left out (OpenCV's default is 4 m; indoor
            robot views reach further, and the far pixels carry the rotation).
        max_translation (m), max_rotation_deg: OpenCV's own plausibility limits on the result.
        max_depth_diff: ICP pairs whose depths differ by more than this (m) are left out; OpenCV
            starts from no motion, so a limit below the step between the frames drops most pairs.
        kind: "rgbd" (ICP + photometric) or "rgb" (photometric only).

    Returns:
        (4, 4) float64 step ``vm_k @ inv(vm_{k-1})``, or None when OpenCV fails.
    """
    settings = cv2.OdometrySettings()
    settings.setCameraMatrix(np.asarray(K, np.float32))
    settings.setMaxDepth(float(max_depth))
    settings.setMaxTranslation(float(max_translation))
    settings.setMaxRotation(float(max_rotation_deg))
    settings.setMaxDepthDiff(float(max_depth_diff))
    otype = {"rgbd": cv2.OdometryType_RGB_DEPTH, "rgb": cv2.OdometryType_RGB}[kind]
    odo = cv2.Odometry(otype, settings, cv2.OdometryAlgoType_COMMON)
    src = cv2.OdometryFrame(depth=np.ascontiguousarray(prev_depth, np.float32), image=_gray(prev_rgb))
    dst = cv2.OdometryFrame(depth=np.ascontiguousarray(depth, np.float32), image=_gray(rgb))
    try:
        odo.prepareFrames(src, dst)
        ok, Rt = odo.compute(src, dst)
    except cv2.error:
        return None
    if not ok or Rt is None or not np.all(np.isfinite(Rt)):
        return None
    return np.asarray(Rt, np.float64)


def rotation_angle(R: np.ndarray) -> float:
    """Angle (rad) of a (3, 3) rotation matrix."""
    return float(np.arccos(np.clip((np.trace(np.asarray(R, np.float64)) - 1) / 2, -1.0, 1.0)))


def camera_displacement(step: np.ndarray) -> np.ndarray:
    """(3,) camera centre ``-R^T t`` of a (4, 4) world-to-camera matrix: for a step, the camera's
    displacement in the previous camera's frame (m)."""
    step = np.asarray(step, np.float64)
    return -step[:3, :3].T @ step[:3, 3]


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(axis, np.float64).reshape(3, 1) * angle)[0]


def planar_yaw_only(step: np.ndarray, up_cam: np.ndarray) -> np.ndarray:
    """``step`` with its rotation replaced by its component about ``up_cam`` (the world's vertical
    axis in the previous camera's frame, (3,)); the camera's displacement is kept."""
    step = np.asarray(step, np.float64)
    up = np.asarray(up_cam, np.float64) / np.linalg.norm(up_cam)
    w = cv2.Rodrigues(step[:3, :3])[0].ravel()
    R = _axis_angle(up, float(w @ up))
    return _with_rotation(step, R)


def horizontal_step(step: np.ndarray, up_cam: np.ndarray) -> np.ndarray:
    """``step`` with the vertical part of its camera displacement removed (``up_cam``: the world's
    vertical in the previous camera's frame, (3,)), for a camera that moves in a horizontal plane."""
    step = np.asarray(step, np.float64)
    up = np.asarray(up_cam, np.float64) / np.linalg.norm(up_cam)
    disp = camera_displacement(step)
    disp = disp - (disp @ up) * up
    out = step.copy()
    out[:3, 3] = -step[:3, :3] @ disp
    return out


def _with_rotation(step: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``step`` with rotation ``R`` and the same camera displacement (-R^T t in the previous frame)."""
    disp = camera_displacement(step)
    out = np.eye(4)
    out[:3, :3] = R
    out[:3, 3] = -R @ disp
    return out


def gate_step(f2f: np.ndarray | None, odo: np.ndarray, sigma_rot: float, sigma_trans: float,
              n_sigma: float = 3.0) -> bool:
    """Whether an OpenCV step ``f2f`` (4, 4) agrees with the wheel odometry's step ``odo`` (4, 4):
    the rotation between them within ``n_sigma`` x ``sigma_rot`` (rad) and the camera
    displacements within ``n_sigma`` x ``sigma_trans`` (m)."""
    if f2f is None:
        return False
    f2f, odo = np.asarray(f2f, np.float64), np.asarray(odo, np.float64)
    d_rot = rotation_angle(f2f[:3, :3] @ odo[:3, :3].T)
    d_trans = float(np.linalg.norm(camera_displacement(f2f) - camera_displacement(odo)))
    return d_rot <= n_sigma * sigma_rot and d_trans <= n_sigma * sigma_trans


def prior_step(odo: np.ndarray, f2f: np.ndarray) -> np.ndarray:
    """The tracker's predicted step: the wheel odometry's displacement with the rotation of the
    accepted frame-to-frame step ``f2f`` (both (4, 4))."""
    return _with_rotation(np.asarray(odo, np.float64), np.asarray(f2f, np.float64)[:3, :3])


def along_step(odo: np.ndarray, f2f: np.ndarray) -> np.ndarray:
    """:func:`prior_step` with, in addition, the camera displacement's component along the wheel
    odometry's direction of motion taken from the accepted frame-to-frame step ``f2f``; the part
    across that direction stays the wheel odometry's (both (4, 4)). A wheeled robot's odometry errs
    in its distance travelled, hardly sideways, while OpenCV's displacement is least fixed across
    the view (a turn against a sideways shift), so each contributes the component it knows best.
    With no motion (an odometry step under 1 mm) this is :func:`prior_step`."""
    odo, f2f = np.asarray(odo, np.float64), np.asarray(f2f, np.float64)
    out = prior_step(odo, f2f)
    d_odo = camera_displacement(odo)
    dist = float(np.linalg.norm(d_odo))
    if dist < 1e-3:
        return out
    u = d_odo / dist
    disp = d_odo + float((camera_displacement(f2f) - d_odo) @ u) * u
    out[:3, 3] = -out[:3, :3] @ disp
    return out
