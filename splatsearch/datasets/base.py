"""What every RGB-D loader shares: the :class:`RGBDSequence` it returns, image reading with clear
errors, intrinsics scaling, undistortion and resizing.

Conventions (the project's): rgb float32 (H, W, 3) in [0, 1]; depth float32 (H, W) metres, 0 =
invalid; ``viewmat`` world-to-camera (4, 4), OpenCV camera frame; ``K`` in pixels with pixel
centres at +0.5. Datasets publish intrinsics in OpenCV's convention (pixel centres at integers),
so :func:`opencv_K` adds half a pixel to the principal point.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import cv2
import numpy as np

from splatsearch.mapper import Frame


@dataclass
class RGBDSequence:
    """Frames of one RGB-D recording.

    Attributes:
        frames: :class:`~splatsearch.mapper.Frame` items; ``viewmat`` is the ground-truth
            world-to-camera pose, or None when the recording has none (then only tracking can map it).
        K: (3, 3) float32 intrinsics of the returned images (after undistortion and resizing).
        width, height: image size in pixels.
        format: the layout it was read as ("tum", "replica", "scannet", "7scenes", "folder", "sim").
        path: the folder it was read from.
        timestamps: (N,) float64 seconds (or frame indices where the layout has no clock).
        names: per-frame source names (the colour file), for error messages and trajectories.
        notes: what the loader did that a user should know (undistortion, resizing, skipped frames).
        odometry: optional (N, 4, 4) world-to-camera poses from the robot's odometry (a prior
            for tracking), None for the datasets.
    """

    frames: list[Frame]
    K: np.ndarray
    width: int
    height: int
    format: str
    path: str
    timestamps: np.ndarray
    names: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    odometry: np.ndarray | None = None

    @property
    def has_gt(self) -> bool:
        """True when every frame has a ground-truth pose (some may be NaN: invalid in the source)."""
        return bool(self.frames) and all(f.viewmat is not None for f in self.frames)

    def __len__(self) -> int:
        return len(self.frames)

    def gt_viewmats(self) -> np.ndarray:
        """(N, 4, 4) ground-truth world-to-camera poses (raises ValueError without ground truth)."""
        if not self.has_gt:
            raise ValueError(f"{self.path}: this sequence has no ground-truth poses")
        return np.stack([f.viewmat for f in self.frames]).astype(np.float64)


def opencv_K(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """(3, 3) float32 K in the project's convention from OpenCV-convention intrinsics."""
    return np.array([[fx, 0, cx + 0.5], [0, fy, cy + 0.5], [0, 0, 1]], np.float32)


def require_dir(path: str, what: str) -> None:
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such folder ({what})")
    if not os.path.isdir(path):
        raise ValueError(f"{path}: not a folder ({what})")


def require_file(path: str, what: str) -> None:
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: missing ({what})")


def read_rgb(path: str) -> np.ndarray:
    """(H, W, 3) float32 RGB in [0, 1] of an 8-bit (or 16-bit) colour image."""
    require_file(path, "colour image")
    img = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: not a readable image")
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, -1)
    if img.shape[2] == 4:
        img = img[..., :3]
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    return np.ascontiguousarray(img[..., ::-1], np.float32) / scale


def read_depth(path: str, scale: float, invalid: int | None = None) -> np.ndarray:
    """(H, W) float32 metres of a 16-bit depth PNG holding ``scale`` units per metre; 0 and
    ``invalid`` (e.g. 7-Scenes' 65535) become 0."""
    require_file(path, "depth image")
    d = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if d is None:
        raise ValueError(f"{path}: not a readable image")
    if d.ndim != 2:
        raise ValueError(f"{path}: depth must be a single-channel image, got shape {d.shape}")
    if d.dtype not in (np.uint16, np.uint32, np.int32, np.float32):
        raise ValueError(f"{path}: depth must be a 16-bit PNG (got {d.dtype}); 8-bit depth loses the range")
    out = d.astype(np.float32)
    if invalid is not None:
        out[d == invalid] = 0.0
    out[~np.isfinite(out)] = 0.0
    return out / np.float32(scale)


def check_size(path: str, img: np.ndarray, width: int, height: int) -> None:
    if img.shape[:2] != (height, width):
        raise ValueError(f"{path}: image is {img.shape[1]}x{img.shape[0]}, expected {width}x{height} "
                         "(every colour and depth image of a sequence must have the calibrated size)")


def read_matrix(path: str, what: str = "4x4 camera-to-world pose") -> np.ndarray:
    """A whitespace-separated 4x4 matrix file (ScanNet, 7-Scenes poses); non-finite entries are
    kept (ScanNet marks lost frames with -inf), the caller treats them as a bad pose."""
    require_file(path, what)
    try:
        m = np.loadtxt(path, dtype=np.float64)
    except ValueError as e:
        raise ValueError(f"{path}: not a {what} ({e})") from None
    if m.size != 16:
        raise ValueError(f"{path}: expected 16 numbers (a {what}), got {m.size}")
    return m.reshape(4, 4)


def c2w_to_viewmat(c2w: np.ndarray) -> np.ndarray:
    """World-to-camera float32 of a camera-to-world 4x4; a non-finite pose gives all NaN."""
    c2w = np.asarray(c2w, np.float64)
    if not np.all(np.isfinite(c2w)):
        return np.full((4, 4), np.nan, np.float32)
    return np.linalg.inv(c2w).astype(np.float32)


class Resampler:
    """Undistorts (radtan k1 k2 p1 p2 k3) and resizes colour and depth to a pinhole camera.

    The undistorted camera is zoomed so that it sees only what the sensor saw (OpenCV's
    ``getOptimalNewCameraMatrix`` with alpha 0): its ``K`` differs from the calibration's.

    Depth is remapped with nearest-neighbour sampling (averaging across an object boundary would
    invent depth between the two surfaces) and resized by taking, per output pixel, the nearest
    source pixel. Colour uses bilinear remapping and area resizing.
    """

    def __init__(self, K: np.ndarray, width: int, height: int, dist=None, downscale: int = 1):
        if downscale < 1 or width % downscale or height % downscale:
            raise ValueError(f"downscale must be >= 1 and divide the image size {width}x{height}, got {downscale}")
        self.src_K = np.asarray(K, np.float32)
        self.src_size = (int(width), int(height))
        self.downscale = int(downscale)
        d = np.zeros(5) if dist is None else np.asarray(dist, np.float64).reshape(-1)
        self.distorted = bool(np.any(d != 0))
        self.maps = None
        self.K = self.src_K.copy()
        if self.distorted:
            # OpenCV works in its own pixel convention: shift the principal point back by 0.5.
            # alpha=0 zooms in until every output pixel samples inside the source image: an
            # undistorted frame has no empty border, which no view could explain consistently.
            Kcv = self.src_K.astype(np.float64).copy()
            Kcv[:2, 2] -= 0.5
            newK, _ = cv2.getOptimalNewCameraMatrix(Kcv, d, self.src_size, 0.0, self.src_size)
            self.maps = cv2.initUndistortRectifyMap(Kcv, d, None, newK, self.src_size, cv2.CV_32FC1)
            self.K = newK.astype(np.float32)
            self.K[:2, 2] += 0.5
        s = self.downscale
        self.K = self.K.copy()
        self.K[:2] /= s  # with centres at +0.5, scaling a pixel grid scales cx, cy exactly
        self.width, self.height = width // s, height // s

    def rgb(self, img: np.ndarray) -> np.ndarray:
        if self.maps is not None:
            img = cv2.remap(img, *self.maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        if self.downscale > 1:
            img = cv2.resize(img, (self.width, self.height), interpolation=cv2.INTER_AREA)
        return np.ascontiguousarray(np.clip(img, 0.0, 1.0), np.float32)

    @property
    def full_K(self) -> np.ndarray:
        """K of the undistorted image before downscaling."""
        K = self.K.copy()
        K[:2] *= self.downscale
        return K

    def depth(self, d: np.ndarray, motion: np.ndarray | None = None) -> np.ndarray:
        """Undistorted, resized depth; ``motion`` (4, 4) moves it from the depth camera's pose
        to the colour camera's (see :func:`warp_depth`) before resizing."""
        if self.maps is not None:
            d = cv2.remap(d, *self.maps, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        if motion is not None:
            d = warp_depth(d, self.full_K, motion)
        if self.downscale > 1:
            s = self.downscale
            d = d[s // 2::s, s // 2::s]
        return np.ascontiguousarray(d, np.float32)


def warp_depth(depth: np.ndarray, K: np.ndarray, motion: np.ndarray) -> np.ndarray:
    """Depth (H, W) seen from another pose: pixels are back-projected, moved by ``motion``
    (4, 4, depth-camera coordinates to target-camera coordinates), projected to their nearest
    pixel and z-buffered (the nearest surface wins). Pixels nothing lands on become invalid."""
    H, W = depth.shape
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    K = np.asarray(K, np.float64)
    x = (u + 0.5 - K[0, 2]) / K[0, 0] * z
    y = (v + 0.5 - K[1, 2]) / K[1, 1] * z
    p = np.stack([x, y, z], 1) @ motion[:3, :3].T + motion[:3, 3]
    ok = p[:, 2] > 1e-3
    p = p[ok]
    u2 = np.floor(K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2]).astype(np.int64)
    v2 = np.floor(K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]).astype(np.int64)
    inside = (u2 >= 0) & (u2 < W) & (v2 >= 0) & (v2 < H)
    out = np.full(H * W, np.inf)
    np.minimum.at(out, v2[inside] * W + u2[inside], p[inside, 2])
    out[~np.isfinite(out)] = 0.0
    return out.reshape(H, W).astype(np.float32)


def sorted_files(folder: str, suffixes: tuple[str, ...], what: str) -> list[str]:
    """Files in ``folder`` ending in one of ``suffixes``, in natural (numeric-aware) order."""
    require_dir(folder, what)
    names = [n for n in os.listdir(folder) if n.lower().endswith(suffixes)]
    if not names:
        raise FileNotFoundError(f"{folder}: no {'/'.join(suffixes)} files ({what})")
    return [os.path.join(folder, n) for n in sorted(names, key=natural_key)]


def natural_key(name: str):
    import re

    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def select(items: list, max_frames: int | None, stride: int) -> list:
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    if max_frames is not None and max_frames < 1:
        raise ValueError(f"max_frames must be >= 1, got {max_frames}")
    out = items[::stride]
    return out if max_frames is None else out[:max_frames]


def make_frame(rgb_path: str, depth_path: str, resampler: Resampler, depth_scale: float, viewmat,
               invalid: int | None = None, depth_size: tuple[int, int] | None = None,
               depth_motion: np.ndarray | None = None) -> Frame:
    """Read, check and resample one frame. ``depth_size``: (W, H) of the depth when it is not the
    colour's (ScanNet): colour is then resized to it before resampling. ``depth_motion``: see
    :meth:`Resampler.depth`."""
    W, H = resampler.src_size
    rgb = read_rgb(rgb_path)
    if depth_size is not None and rgb.shape[:2] != (H, W):
        rgb = cv2.resize(rgb, (W, H), interpolation=cv2.INTER_AREA)
    check_size(rgb_path, rgb, W, H)
    depth = read_depth(depth_path, depth_scale, invalid)
    check_size(depth_path, depth, W, H)
    vm = None if viewmat is None else np.asarray(viewmat, np.float32)
    return Frame(resampler.rgb(rgb), resampler.depth(depth, depth_motion), vm)
