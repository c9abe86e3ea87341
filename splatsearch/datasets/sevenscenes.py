"""Microsoft 7-Scenes sequences.

Layout: ``seq-XX/frame-NNNNNN.color.png``, ``.depth.png`` (16-bit millimetres, 65535 = invalid)
and ``.pose.txt`` (camera-to-world 4x4). The path is a ``seq-XX`` folder, or a scene folder that
holds exactly one of them. The Kinect's depth is not registered to its colour camera in this
dataset; the usual intrinsics (585, 585, 320, 240) are applied to both.
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
    read_matrix,
    require_dir,
    select,
    sorted_files,
)

SEVEN_SCENES_CAMERA = {"fx": 585.0, "fy": 585.0, "cx": 320.0, "cy": 240.0, "w": 640, "h": 480}
INVALID_DEPTH = 65535


def _seq_dir(path: str) -> str:
    require_dir(path, "a 7-Scenes seq-XX folder")
    if any(n.endswith(".color.png") for n in os.listdir(path)):
        return path
    seqs = sorted(n for n in os.listdir(path) if n.startswith("seq-") and os.path.isdir(os.path.join(path, n)))
    if len(seqs) == 1:
        return os.path.join(path, seqs[0])
    if not seqs:
        raise FileNotFoundError(f"{path}: no frame-NNNNNN.color.png files and no seq-XX folder (7-Scenes)")
    raise ValueError(f"{path}: holds {len(seqs)} sequences ({', '.join(seqs[:4])}...): pass one seq-XX folder")


def load_7scenes(path: str, max_frames: int | None = None, stride: int = 1, *, downscale: int = 1,
                 require_poses: bool = True) -> RGBDSequence:
    """Load one 7-Scenes sequence folder."""
    seq = _seq_dir(path)
    colours = sorted_files(seq, (".color.png",), "7-Scenes frames")
    cam = SEVEN_SCENES_CAMERA
    res = Resampler(opencv_K(cam["fx"], cam["fy"], cam["cx"], cam["cy"]), cam["w"], cam["h"], None, downscale)
    items = select(colours, max_frames, stride)
    frames = []
    for cp in items:
        base = cp[: -len(".color.png")]
        pose_path = base + ".pose.txt"
        vm = None
        if require_poses or os.path.exists(pose_path):
            vm = c2w_to_viewmat(read_matrix(pose_path))
        frames.append(make_frame(cp, base + ".depth.png", res, 1000.0, vm, invalid=INVALID_DEPTH))
    idx = np.array([float(os.path.basename(p)[6:12]) if os.path.basename(p)[6:12].isdigit() else i
                    for i, p in enumerate(items)])
    return RGBDSequence(frames, res.K, res.width, res.height, "7scenes", seq, idx,
                        [os.path.basename(p) for p in items],
                        ["7-Scenes depth is not registered to colour: expect colour/depth misalignment at edges"])
