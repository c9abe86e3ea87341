"""TUM RGB-D benchmark folders (Sturm et al., IROS 2012).

Layout: ``rgb.txt`` and ``depth.txt`` (``timestamp filename`` lines), ``rgb/``, ``depth/`` (16-bit
PNG, 5000 per metre, 0 = invalid) and ``groundtruth.txt`` (``timestamp tx ty tz qx qy qz qw``,
camera-to-world of the RGB optical frame). RGB and depth are associated by nearest timestamp as
TUM's ``associate.py`` does; ground truth is interpolated (lerp + slerp) at each RGB timestamp.

Intrinsics: an ``intrinsics.json`` beside the lists wins; otherwise the sequence's calibration
(freiburg1/2/3, from the folder name) from :data:`TUM_INTRINSICS`, with its radial-tangential
distortion removed by :class:`~splatsearch.datasets.base.Resampler`; otherwise TUM's ROS
defaults (525, 525, 319.5, 239.5, no distortion).
"""

from __future__ import annotations

import json
import os
import re

import numpy as np

from splatsearch.datasets.base import (
    Resampler,
    RGBDSequence,
    c2w_to_viewmat,
    make_frame,
    opencv_K,
    require_dir,
    require_file,
    select,
)

#: Calibrated TUM RGB-D intrinsics (OpenCV convention) and radtan distortion (k1 k2 p1 p2 k3),
#: from the benchmark's "file formats / intrinsic camera calibration" page.
TUM_INTRINSICS = {
    "fr1": {"fx": 517.3, "fy": 516.5, "cx": 318.6, "cy": 255.3,
            "distortion": [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]},
    "fr2": {"fx": 520.9, "fy": 521.0, "cx": 325.1, "cy": 249.7,
            "distortion": [0.2312, -0.7849, -0.0033, -0.0001, 0.9172]},
    "fr3": {"fx": 535.4, "fy": 539.2, "cx": 320.1, "cy": 247.6, "distortion": [0.0, 0.0, 0.0, 0.0, 0.0]},
    "ros_default": {"fx": 525.0, "fy": 525.0, "cx": 319.5, "cy": 239.5, "distortion": [0.0, 0.0, 0.0, 0.0, 0.0]},
}
TUM_DEPTH_SCALE = 5000.0


def read_list(path: str) -> list[tuple[float, list[str]]]:
    """``timestamp value...`` lines of a TUM list file; '#' comments and header lines skipped."""
    require_file(path, "TUM list file")
    out = []
    with open(path) as f:
        for line in f:
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            parts = line.split()
            try:
                out.append((float(parts[0]), parts[1:]))
            except ValueError:  # a header line without '#', e.g. "timestamp tx ty tz qx qy qz qw"
                continue
    return out


def quat_to_R(q) -> np.ndarray:
    """(3, 3) rotation of a quaternion (x, y, z, w), normalised first."""
    x, y, z, w = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def slerp(q0, q1, t: float) -> np.ndarray:
    q0, q1 = q0 / np.linalg.norm(q0), q1 / np.linalg.norm(q1)
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + t * (q1 - q0)
        return q / np.linalg.norm(q)
    th = np.arccos(d)
    return (np.sin((1 - t) * th) * q0 + np.sin(t * th) * q1) / np.sin(th)


def interpolate_pose(gt: np.ndarray, t: float, max_gap: float = 0.1) -> np.ndarray | None:
    """Camera-to-world (4, 4) at time ``t`` from (M, 8) ``timestamp tx ty tz qx qy qz qw`` rows,
    or None outside the recording or across a gap in the motion capture longer than ``max_gap`` s."""
    if len(gt) == 0 or t < gt[0, 0] or t > gt[-1, 0]:
        return None
    k = int(np.searchsorted(gt[:, 0], t))
    k = min(max(k, 1), len(gt) - 1)
    dt = gt[k, 0] - gt[k - 1, 0]
    if dt > max_gap:
        return None
    a = (t - gt[k - 1, 0]) / max(dt, 1e-9)
    c2w = np.eye(4)
    c2w[:3, :3] = quat_to_R(slerp(gt[k - 1, 4:8], gt[k, 4:8], a))
    c2w[:3, 3] = (1 - a) * gt[k - 1, 1:4] + a * gt[k, 1:4]
    return c2w


def tum_intrinsics(path: str) -> tuple[dict, str]:
    """(intrinsics dict with fx fy cx cy distortion depth_scale, where it came from)."""
    intr_path = os.path.join(path, "intrinsics.json")
    if os.path.exists(intr_path):
        try:
            with open(intr_path) as f:
                intr = json.load(f)
            dist = intr.get("distortion", [0.0] * 5)
            if isinstance(dist, dict):
                dist = dist.get("coeffs", [0.0] * 5)
            return ({"fx": float(intr["fx"]), "fy": float(intr["fy"]), "cx": float(intr["cx"]),
                     "cy": float(intr["cy"]), "distortion": [float(v) for v in dist],
                     "depth_scale": float(intr.get("depth_scale", TUM_DEPTH_SCALE))}, intr_path)
        except (KeyError, TypeError, ValueError, json.JSONDecodeError) as e:
            raise ValueError(f"{intr_path}: expected JSON with fx, fy, cx, cy ({e})") from None
    name = os.path.basename(os.path.normpath(os.path.abspath(path))).lower()
    m = re.search(r"(?:freiburg|fr)([123])", name)
    key = f"fr{m.group(1)}" if m else "ros_default"
    return dict(TUM_INTRINSICS[key], depth_scale=TUM_DEPTH_SCALE), f"TUM {key} calibration"


def load_tum(path: str, max_frames: int | None = None, stride: int = 1, max_dt: float = 0.02, *,
             downscale: int = 1, undistort: bool = True, require_poses: bool = True,
             sync_depth: bool = False) -> RGBDSequence:
    """Load a TUM RGB-D folder.

    Args:
        path: folder with rgb.txt, depth.txt, rgb/, depth/ and groundtruth.txt.
        max_frames, stride: keep every ``stride``-th associated frame, at most ``max_frames``.
        max_dt: largest RGB-depth timestamp difference for an association (s).
        downscale: integer factor (2: 640x480 -> 320x240).
        undistort: remove the calibrated lens distortion (fr1, fr2).
        require_poses: without groundtruth.txt raise FileNotFoundError; if False, frames get
            ``viewmat=None`` (to be tracked).
        sync_depth: the Kinect takes depth ~15 ms before colour; move each depth image to the
            colour image's instant with the ground-truth motion between the two timestamps
            (a pixel or two while the camera moves). Uses ground truth: only for mapping with
            ground-truth poses, never when the poses are to be tracked.

    Frames outside the ground truth's time span are skipped (and counted in ``notes``).
    """
    require_dir(path, "a TUM RGB-D folder")
    rgb_txt, depth_txt, gt_txt = (os.path.join(path, n) for n in ("rgb.txt", "depth.txt", "groundtruth.txt"))
    require_file(rgb_txt, "TUM rgb.txt")
    require_file(depth_txt, "TUM depth.txt")
    has_gt = os.path.exists(gt_txt)
    if require_poses and not has_gt:
        raise FileNotFoundError(f"{gt_txt}: missing (TUM ground truth; run with --track to map without it)")
    intr, source = tum_intrinsics(path)
    W, H = 640, 480
    res = Resampler(opencv_K(intr["fx"], intr["fy"], intr["cx"], intr["cy"]), W, H,
                    intr["distortion"] if undistort else None, downscale)
    rgbs, depths = read_list(rgb_txt), read_list(depth_txt)
    if not rgbs or not depths:
        raise ValueError(f"{path}: rgb.txt or depth.txt lists no frames")
    if any(len(v) < 1 for _, v in rgbs + depths):
        raise ValueError(f"{path}: rgb.txt / depth.txt lines must be 'timestamp filename'")
    gt = None
    if has_gt:
        rows = read_list(gt_txt)
        try:
            gt = np.array([[t] + [float(v) for v in vals] for t, vals in rows], np.float64)
        except ValueError:
            gt = np.zeros((0, 0))
        if gt.ndim != 2 or gt.shape[1] != 8:
            raise ValueError(f"{gt_txt}: expected lines 'timestamp tx ty tz qx qy qz qw'")
        gt = gt[np.argsort(gt[:, 0])]
    dts = np.array([t for t, _ in depths])
    pairs, no_gt = [], 0
    for t, vals in rgbs:
        j = int(np.argmin(np.abs(dts - t)))
        if abs(dts[j] - t) > max_dt:
            continue
        c2w = None
        if gt is not None:
            c2w = interpolate_pose(gt, t)
            if c2w is None:
                no_gt += 1
                continue
        motion = None
        if sync_depth and c2w is not None:
            c2w_d = interpolate_pose(gt, dts[j])
            if c2w_d is not None:  # depth-camera coordinates -> colour-camera coordinates
                motion = np.linalg.inv(c2w) @ c2w_d
        pairs.append((t, vals[0], depths[j][1][0], c2w, motion))
    pairs = select(pairs, max_frames, stride)
    if not pairs:
        raise ValueError(f"{path}: no RGB frame could be associated with a depth image"
                         + (" and the ground truth" if gt is not None else "") + f" within {max_dt} s")
    if sync_depth and gt is None:
        raise ValueError(f"{path}: sync_depth needs ground truth (groundtruth.txt)")
    frames = [make_frame(os.path.join(path, rf), os.path.join(path, df), res, intr["depth_scale"],
                         None if c2w is None else c2w_to_viewmat(c2w), depth_motion=mo)
              for _, rf, df, c2w, mo in pairs]
    notes = [f"intrinsics: {source}"]
    if res.distorted:
        notes.append("lens distortion removed (radtan)")
    if sync_depth:
        notes.append("depth moved to the colour timestamps with the ground-truth motion")
    if no_gt:
        notes.append(f"{no_gt} frames outside the ground truth's time span skipped")
    return RGBDSequence(frames, res.K, res.width, res.height, "tum", path, np.array([p[0] for p in pairs]),
                        [p[1] for p in pairs], notes)
