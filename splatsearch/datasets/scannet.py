"""ScanNet exports (the SensReader ``export`` layout SplaTAM reads).

Layout: ``color/N.jpg`` (1296x968), ``depth/N.png`` (16-bit millimetres, 640x480), ``pose/N.txt``
(camera-to-world 4x4; lost frames hold ``-inf``) and ``intrinsic/intrinsic_depth.txt`` /
``intrinsic_color.txt`` (4x4). Colour is resized to the depth image (which is registered to it)
and the depth intrinsics are used; a frame whose pose is not finite keeps a NaN viewmat, which
mapping skips.
"""

from __future__ import annotations

import os

import numpy as np

from splatsearch.datasets.base import (
    Resampler,
    RGBDSequence,
    c2w_to_viewmat,
    make_frame,
    opencv_K,
    read_depth,
    read_matrix,
    require_dir,
    select,
    sorted_files,
)


def load_scannet(path: str, max_frames: int | None = None, stride: int = 1, *, downscale: int = 1,
                 require_poses: bool = True, depth_scale: float = 1000.0) -> RGBDSequence:
    """Load a ScanNet export folder (``color/``, ``depth/``, ``pose/``, ``intrinsic/``)."""
    require_dir(path, "a ScanNet export folder")
    colours = sorted_files(os.path.join(path, "color"), (".jpg", ".png"), "ScanNet color/")
    intr_dir = os.path.join(path, "intrinsic")
    require_dir(intr_dir, "ScanNet intrinsic/")
    kd = os.path.join(intr_dir, "intrinsic_depth.txt")
    kc = os.path.join(intr_dir, "intrinsic_color.txt")
    pose_dir = os.path.join(path, "pose")
    if require_poses:
        require_dir(pose_dir, "ScanNet pose/")
    items = select(colours, max_frames, stride)
    stem = lambda p: os.path.splitext(os.path.basename(p))[0]  # noqa: E731
    d0 = read_depth(os.path.join(path, "depth", stem(items[0]) + ".png"), depth_scale)
    H, W = d0.shape
    if os.path.exists(kd):
        Km = read_matrix(kd, "4x4 depth intrinsics")
    else:
        from splatsearch.datasets.base import read_rgb

        Km = read_matrix(kc, "4x4 colour intrinsics")
        h, w = read_rgb(items[0]).shape[:2]
        Km[0] *= W / w
        Km[1] *= H / h
    res = Resampler(opencv_K(Km[0, 0], Km[1, 1], Km[0, 2], Km[1, 2]), W, H, None, downscale)
    frames = []
    has_poses = os.path.isdir(pose_dir)
    for cp in items:
        vm = c2w_to_viewmat(read_matrix(os.path.join(pose_dir, stem(cp) + ".txt"))) if has_poses else None
        frames.append(make_frame(cp, os.path.join(path, "depth", stem(cp) + ".png"), res, depth_scale, vm,
                                 depth_size=(W, H)))
    bad = sum(1 for f in frames if f.viewmat is not None and not np.all(np.isfinite(f.viewmat)))
    notes = ["colour resized to the depth resolution; depth intrinsics"]
    if bad:
        notes.append(f"{bad} frames have no valid ground-truth pose (-inf in pose/)")
    ts = []
    for p in items:
        try:
            ts.append(float(stem(p)))
        except ValueError:
            ts.append(float(len(ts)))
    return RGBDSequence(frames, res.K, res.width, res.height, "scannet", path, np.array(ts),
                        [os.path.relpath(p, path) for p in items], notes)
