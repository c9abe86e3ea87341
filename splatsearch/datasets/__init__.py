"""RGB-D frame sources for the mapper: the standard dataset layouts and simulator walks.

    seq = load_sequence("rgbd_dataset_freiburg1_desk")          # layout detected
    seq = load_sequence(path, format="replica", downscale=2)    # 1200x680 -> 600x340
    seq.frames[i].rgb / .depth / .viewmat (ground truth or None); seq.K, seq.width, seq.height

One module per layout: :mod:`.tum`, :mod:`.replica`, :mod:`.scannet`, :mod:`.sevenscenes`,
:mod:`.folder`; :mod:`.sim` for simulator walks with noisy odometry. Loaders raise
FileNotFoundError for a missing folder or file and ValueError for a malformed one, naming the
path.
"""

from __future__ import annotations

import os

from splatsearch.datasets.base import RGBDSequence
from splatsearch.datasets.folder import load_folder
from splatsearch.datasets.replica import load_replica
from splatsearch.datasets.scannet import load_scannet
from splatsearch.datasets.sevenscenes import load_7scenes
from splatsearch.datasets.sim import noisy_odometry, sim_trajectory, sim_walk
from splatsearch.datasets.tum import TUM_INTRINSICS, load_tum

FORMATS = ("tum", "replica", "scannet", "7scenes", "folder")
_LOADERS = {"tum": load_tum, "replica": load_replica, "scannet": load_scannet, "7scenes": load_7scenes,
            "folder": load_folder}


def detect_format(path: str) -> str:
    """The layout of ``path``: one of :data:`FORMATS` (FileNotFoundError / ValueError otherwise)."""
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such folder")
    if not os.path.isdir(path):
        raise ValueError(f"{path}: not a folder (expected an RGB-D dataset folder)")
    has = lambda *names: all(os.path.exists(os.path.join(path, n)) for n in names)  # noqa: E731
    if has("rgb.txt", "depth.txt"):
        return "tum"
    if os.path.isdir(os.path.join(path, "results")) and any(
            n.startswith("frame") for n in os.listdir(os.path.join(path, "results"))):
        return "replica"
    if has("color", "depth", "intrinsic"):
        return "scannet"
    names = os.listdir(path)
    if any(n.endswith(".color.png") for n in names) or any(
            n.startswith("seq-") and os.path.isdir(os.path.join(path, n)) for n in names):
        return "7scenes"
    if has("rgb", "depth", "intrinsics.json"):
        return "folder"
    raise ValueError(f"{path}: unknown RGB-D layout; expected TUM (rgb.txt, depth.txt), Replica (results/frame*.jpg, "
                     "traj.txt), ScanNet (color/, depth/, pose/, intrinsic/), 7-Scenes (seq-XX/frame-*.color.png) "
                     "or a folder (rgb/, depth/, intrinsics.json[, poses.txt])")


def load_sequence(path: str, format: str = "auto", *, max_frames: int | None = None, stride: int = 1,
                  downscale: int = 1, require_poses: bool = True, undistort: bool = True,
                  sync_depth: bool = False) -> RGBDSequence:
    """Load an RGB-D recording.

    Args:
        path: the dataset folder.
        format: "auto" (detect) or one of :data:`FORMATS`.
        max_frames, stride: keep every ``stride``-th frame, at most ``max_frames``.
        downscale: integer image size divisor (intrinsics follow).
        require_poses: without a ground-truth pose file raise FileNotFoundError; if False the
            frames get ``viewmat=None`` (map them with tracking).
        undistort: remove calibrated lens distortion where the layout has it (TUM fr1/fr2, folder).
        sync_depth: TUM only: move depth to the colour timestamps with the ground-truth motion
            (see :func:`~splatsearch.datasets.tum.load_tum`).
    """
    if format == "auto":
        format = detect_format(path)
    if format not in _LOADERS:
        raise ValueError(f"unknown format {format!r}; expected auto or one of {', '.join(FORMATS)}")
    kw = {"max_frames": max_frames, "stride": stride, "downscale": downscale, "require_poses": require_poses}
    if format in ("tum", "folder"):
        kw["undistort"] = undistort
    if sync_depth:
        if format != "tum":
            raise ValueError(f"sync_depth is for TUM sequences (depth and colour timestamps), not {format}")
        kw["sync_depth"] = True
    return _LOADERS[format](path, **kw)


__all__ = ["FORMATS", "TUM_INTRINSICS", "RGBDSequence", "detect_format", "load_7scenes", "load_folder",
           "load_replica", "load_scannet", "load_sequence", "load_tum", "noisy_odometry", "sim_trajectory",
           "sim_walk"]
