"""A generic RGB-D folder, for a user's own sensor.

Layout::

    rgb/        colour images (png or jpg), sorted by name
    depth/      16-bit depth PNGs with the same names (stems), ``depth_scale`` per metre, 0 = invalid
    intrinsics.json  {"fx", "fy", "cx", "cy"[, "depth_scale" (default 1000), "distortion": [k1 k2 p1 p2 k3]]}
                     OpenCV convention (pixel centres at integers)
    poses.txt   optional: one camera-to-world pose a line, either 16 numbers (row-major 4x4),
                ``tx ty tz qx qy qz qw`` or TUM's ``timestamp tx ty tz qx qy qz qw``

Without ``poses.txt`` the frames have no ground truth and can only be mapped with tracking.
"""

from __future__ import annotations

import json
import os

import cv2
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
    sorted_files,
)
from splatsearch.datasets.tum import quat_to_R


def read_poses(path: str) -> tuple[np.ndarray, np.ndarray | None]:
    """((N, 4, 4) camera-to-world, (N,) timestamps or None) of a poses.txt (see the module doc)."""
    require_file(path, "poses.txt")
    mats, ts = [], []
    with open(path) as f:
        for i, line in enumerate(f, 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            try:
                v = [float(x) for x in line.split()]
            except ValueError:
                raise ValueError(f"{path}:{i}: expected numbers, got {line[:60]!r}") from None
            if len(v) == 16:
                mats.append(np.array(v).reshape(4, 4))
            elif len(v) in (7, 8):
                if len(v) == 8:
                    ts.append(v[0])
                    v = v[1:]
                m = np.eye(4)
                m[:3, :3] = quat_to_R(v[3:7]) if np.all(np.isfinite(v[3:7])) else np.nan
                m[:3, 3] = v[:3]
                mats.append(m)
            else:
                raise ValueError(f"{path}:{i}: expected 16 numbers (4x4), 7 (tx ty tz qx qy qz qw) or 8 "
                                 f"(timestamp first), got {len(v)}")
    if ts and len(ts) != len(mats):
        raise ValueError(f"{path}: mixes lines with and without timestamps")
    return np.array(mats).reshape(-1, 4, 4), (np.array(ts) if ts else None)


def load_folder(path: str, max_frames: int | None = None, stride: int = 1, *, downscale: int = 1,
                undistort: bool = True, require_poses: bool = True) -> RGBDSequence:
    """Load a generic ``rgb/``, ``depth/``, ``intrinsics.json``, ``poses.txt`` folder."""
    require_dir(path, "an RGB-D folder")
    intr_path = os.path.join(path, "intrinsics.json")
    require_file(intr_path, "intrinsics.json with fx, fy, cx, cy")
    try:
        with open(intr_path) as f:
            intr = json.load(f)
        fx, fy, cx, cy = (float(intr[k]) for k in ("fx", "fy", "cx", "cy"))
        scale = float(intr.get("depth_scale", 1000.0))
        dist = intr.get("distortion")
        if isinstance(dist, dict):
            dist = dist.get("coeffs")
    except (KeyError, TypeError, ValueError, json.JSONDecodeError) as e:
        raise ValueError(f"{intr_path}: expected JSON with fx, fy, cx, cy ({e})") from None
    colours = sorted_files(os.path.join(path, "rgb"), (".png", ".jpg", ".jpeg"), "rgb/")
    depth_dir = os.path.join(path, "depth")
    require_dir(depth_dir, "depth/")
    by_stem = {os.path.splitext(n)[0]: os.path.join(depth_dir, n) for n in os.listdir(depth_dir)}
    pose_path = os.path.join(path, "poses.txt")
    c2ws = ts = None
    if require_poses or os.path.exists(pose_path):
        c2ws, ts = read_poses(pose_path)
        if len(c2ws) != len(colours):
            raise ValueError(f"{pose_path}: {len(c2ws)} poses for {len(colours)} images in rgb/")
    probe = cv2.imread(colours[0], cv2.IMREAD_UNCHANGED)
    if probe is None:
        raise ValueError(f"{colours[0]}: not a readable image")
    H, W = probe.shape[:2]
    W = int(intr.get("width", W))
    H = int(intr.get("height", H))
    res = Resampler(opencv_K(fx, fy, cx, cy), W, H, dist if undistort else None, downscale)
    items = select(list(enumerate(colours)), max_frames, stride)
    frames = []
    for i, cp in items:
        stem = os.path.splitext(os.path.basename(cp))[0]
        if stem not in by_stem:
            raise FileNotFoundError(f"{os.path.join(depth_dir, stem)}.png: missing (depth for {cp})")
        frames.append(make_frame(cp, by_stem[stem], res, scale, None if c2ws is None else c2w_to_viewmat(c2ws[i])))
    stamps = np.array([ts[i] if ts is not None else float(i) for i, _ in items])
    return RGBDSequence(frames, res.K, res.width, res.height, "folder", path, stamps,
                        [os.path.relpath(cp, path) for _, cp in items],
                        ["lens distortion removed (radtan)"] if res.distorted else [])
