"""Replica as NICE-SLAM and SplaTAM ship it.

Layout: ``results/frameNNNNNN.jpg``, ``results/depthNNNNNN.png`` (16-bit, 6553.5 per metre) and
``traj.txt`` (one camera-to-world 4x4 per line, row-major, OpenCV camera frame). Intrinsics come
from a ``cam_params.json`` in the folder or its parent (Replica's ``{"camera": {"w", "h", "fx",
"fy", "cx", "cy", "scale"}}``), else the values every Replica sequence shares (1200x680, f 600,
centre 599.5, 339.5).
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
    sorted_files,
)

REPLICA_CAMERA = {"w": 1200, "h": 680, "fx": 600.0, "fy": 600.0, "cx": 599.5, "cy": 339.5, "scale": 6553.5}


def read_traj(path: str) -> np.ndarray:
    """(N, 4, 4) camera-to-world poses of a NICE-SLAM ``traj.txt`` (16 numbers a line)."""
    require_file(path, "Replica traj.txt")
    rows = []
    with open(path) as f:
        for i, line in enumerate(f, 1):
            if not line.strip():
                continue
            try:
                vals = [float(v) for v in line.split()]
            except ValueError:
                raise ValueError(f"{path}:{i}: expected 16 numbers, got {line.strip()[:60]!r}") from None
            if len(vals) != 16:
                raise ValueError(f"{path}:{i}: expected 16 numbers (a row-major 4x4), got {len(vals)}")
            rows.append(vals)
    return np.array(rows, np.float64).reshape(-1, 4, 4)


def _camera(path: str) -> tuple[dict, str]:
    for p in (os.path.join(path, "cam_params.json"), os.path.join(os.path.dirname(os.path.abspath(path)),
                                                                   "cam_params.json")):
        if os.path.exists(p):
            try:
                with open(p) as f:
                    cam = json.load(f)["camera"]
                return {k: float(cam[k]) for k in REPLICA_CAMERA}, p
            except (KeyError, TypeError, ValueError, json.JSONDecodeError) as e:
                raise ValueError(f"{p}: expected {{'camera': {{w, h, fx, fy, cx, cy, scale}}}} ({e})") from None
    return dict(REPLICA_CAMERA), "Replica defaults"


def load_replica(path: str, max_frames: int | None = None, stride: int = 1, *, downscale: int = 1,
                 require_poses: bool = True) -> RGBDSequence:
    """Load a NICE-SLAM-style Replica sequence folder (``results/``, ``traj.txt``)."""
    require_dir(path, "a Replica sequence folder")
    results = os.path.join(path, "results")
    colours = [p for p in sorted_files(results, (".jpg", ".png"), "Replica results/")
               if re.match(r"frame\d+\.(jpg|png)$", os.path.basename(p))]
    if not colours:
        raise FileNotFoundError(f"{results}: no frameNNNNNN.jpg files")
    traj_path = os.path.join(path, "traj.txt")
    c2ws = None
    if os.path.exists(traj_path) or require_poses:
        c2ws = read_traj(traj_path)
        if len(c2ws) < len(colours):
            raise ValueError(f"{traj_path}: {len(c2ws)} poses for {len(colours)} frames")
    cam, source = _camera(path)
    res = Resampler(opencv_K(cam["fx"], cam["fy"], cam["cx"], cam["cy"]), int(cam["w"]), int(cam["h"]),
                    None, downscale)
    items = select(list(enumerate(colours)), max_frames, stride)
    frames, names = [], []
    for i, cp in items:
        num = re.search(r"(\d+)", os.path.basename(cp)).group(1)
        dp = os.path.join(results, f"depth{num}.png")
        frames.append(make_frame(cp, dp, res, cam["scale"], None if c2ws is None else c2w_to_viewmat(c2ws[i])))
        names.append(os.path.relpath(cp, path))
    return RGBDSequence(frames, res.K, res.width, res.height, "replica", path,
                        np.array([float(i) for i, _ in items]), names, [f"intrinsics: {source}"])
