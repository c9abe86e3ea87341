"""Object-local Gaussian maps for the NVSM.

An online map of a whole house, at the resolution and iteration count that a CPU can afford per
step, renders novel views too soft for SIFT to tell instances apart; the object's own
observations carry the detail. So each object keeps a few full-resolution RGB-D observations from distinct
viewpoints (:class:`ObservationStore`), and when its NVSM is due a small map of the object and its
surroundings (its extent grown by ``margin``) is built from them at full resolution
(:func:`build_local_map`). Rendering that map around the hemisphere gives the NVSM views; pixels
that see nothing of the region are background, not holes (see :func:`verify_local`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from splatsearch.camera import pixels_to_world
from splatsearch.gaussians import GaussianMap
from splatsearch.mapper import Frame, Mapper, MapperConfig

from .novel_views import camera_pose, crop_box_for


@dataclass
class LocalMapConfig:
    """Settings of the object-local maps.

    Attributes:
        margin: metres of surroundings kept around the object's extent (the goal image shows the
            object in its surroundings, which carry many of the matches).
        max_frames: observations kept per object (the most redundant viewpoint is dropped).
        iters_per_frame: Adam steps when each observation is added; refine_iters: steps over all
            of them at the end (the Gaussians start with their pixels' colours and depths, so few
            steps are needed; measurements in ``docs/results.md``). stride: densify stride in
            pixels (1: a Gaussian per observed pixel; the NVSM's matches come from the covered
            part of the render, which a coarser stride blurs).
        capacity: initial Gaussian capacity (grows by doubling).
        min_separation: metres; an observation closer than this to a kept one (camera centres)
            with a heading within 20 degrees replaces it instead of adding a viewpoint.
        surface_init: Gaussians start as flat ellipses in the surface plane
            (:attr:`splatsearch.mapper.MapperConfig.surface_init`).
    """

    margin: float = 3.0
    max_frames: int = 5
    iters_per_frame: int = 4
    refine_iters: int = 16
    stride: int = 1
    capacity: int = 16384
    min_separation: float = 0.3
    surface_init: bool = True

    def __post_init__(self):
        if not (self.margin >= 0 and self.max_frames >= 1 and self.iters_per_frame >= 0 and self.refine_iters >= 0
                and self.stride >= 1 and self.capacity >= 1):
            raise ValueError(f"invalid LocalMapConfig: {self}")


class ObservationStore:
    """Up to ``max_frames`` full-resolution observations per object entry.

    Observations are kept for viewpoint diversity: when the store of an entry is full, the new
    observation replaces the kept one nearest to another kept one (camera centre distance plus
    heading), unless the new one is itself the most redundant.
    """

    def __init__(self, max_frames: int = 5, min_separation: float = 0.3):
        if max_frames < 1:
            raise ValueError(f"max_frames must be >= 1, got {max_frames}")
        self.max_frames, self.min_separation = int(max_frames), float(min_separation)
        self._frames: dict[int, list[Frame]] = {}

    def __getitem__(self, entry_id: int) -> list[Frame]:
        return self._frames.get(entry_id, [])

    @staticmethod
    def _dist(a: Frame, b: Frame) -> float:
        ca, fa = camera_pose(a.viewmat)
        cb, fb = camera_pose(b.viewmat)
        # 1 m of travel ~ 60 degrees of turn: both change what the camera sees by about as much
        return float(np.linalg.norm(ca - cb) + np.arccos(np.clip(fa @ fb, -1.0, 1.0)))

    def add(self, entry_id: int, rgb: np.ndarray, depth: np.ndarray, viewmat: np.ndarray) -> None:
        """Keep one observation of ``entry_id``: rgb (H, W, 3) in [0, 1], depth (H, W) metres,
        viewmat (4, 4) world-to-camera. The arrays are copied."""
        f = Frame(np.array(rgb, np.float32), np.array(depth, np.float32), np.array(viewmat, np.float32))
        if f.rgb.ndim != 3 or f.depth.shape != f.rgb.shape[:2] or f.viewmat.shape != (4, 4):
            raise ValueError(f"expected rgb (H, W, 3), depth (H, W), viewmat (4, 4); got "
                             f"{f.rgb.shape}, {f.depth.shape}, {f.viewmat.shape}")
        kept = self._frames.setdefault(entry_id, [])
        c_new, f_new = camera_pose(f.viewmat)
        for i, k in enumerate(kept):
            c, fw = camera_pose(k.viewmat)
            if np.linalg.norm(c - c_new) < self.min_separation and fw @ f_new > np.cos(np.radians(20)):
                kept[i] = f  # the same viewpoint: the newer view (of a better map pose) wins
                return
        kept.append(f)
        if len(kept) > self.max_frames:
            n = len(kept)
            d = np.array([[self._dist(kept[i], kept[j]) if i != j else np.inf for j in range(n)] for i in range(n)])
            kept.pop(int(np.argmin(d.min(1))))


def region_frame(rgb: np.ndarray, depth: np.ndarray, viewmat: np.ndarray, K: np.ndarray,
                 lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Blank out the pixels whose 3-D point lies outside the world box [lo, hi].

    Those pixels get depth 0 (invalid: nothing is densified there, no depth loss) and black
    colour, which is what an empty region renders as, so the photometric loss does not make the
    region's Gaussians grow to paint the rest of the house.

    Returns (rgb (H, W, 3), depth (H, W)) copies.
    """
    H, W = depth.shape
    rows, cols = np.mgrid[0:H, 0:W]
    pw = pixels_to_world(cols, rows, depth, viewmat, K)
    inside = (depth > 0) & np.all((pw >= lo) & (pw <= hi), axis=-1)
    rgb_out = np.where(inside[..., None], rgb, 0.0).astype(np.float32)
    return rgb_out, np.where(inside, depth, 0.0).astype(np.float32)


def region_box(bbox_min: Sequence[float], bbox_max: Sequence[float], margin: float) -> tuple[np.ndarray, np.ndarray]:
    """The object's extent grown by ``margin`` metres, floor kept, as (lo (3,), hi (3,))."""
    return crop_box_for(bbox_min, bbox_max, margin, floor_z=None)


def build_local_map(frames: Sequence[Frame], K: np.ndarray, width: int, height: int, lo: np.ndarray, hi: np.ndarray,
                    config: LocalMapConfig | None = None, *, seed: int = 0) -> GaussianMap:
    """A Gaussian map of the world box [lo, hi] from posed full-resolution observations.

    Args:
        frames: the observations (see :class:`ObservationStore`), each at ``width`` x ``height``.
        K: (3, 3) intrinsics in pixels.
        lo, hi: (3,) the region in metres (see :func:`region_box`).
        config: :class:`LocalMapConfig`.
    """
    cfg = config or LocalMapConfig()
    if not frames:
        raise ValueError("need at least one observation to build a local map")
    K = np.asarray(K, np.float32)
    lo, hi = np.asarray(lo, np.float32), np.asarray(hi, np.float32)
    mapper = Mapper(K, width, height, MapperConfig(
        iters=cfg.iters_per_frame, stride=cfg.stride, window=max(2, len(frames)), keyframe_every=1,
        window_select="recent", initial_capacity=cfg.capacity, seed=seed, surface_init=cfg.surface_init))
    for f in frames:
        rgb, depth = region_frame(f.rgb, f.depth, f.viewmat, K, lo, hi)
        mapper.update(rgb, depth, f.viewmat)
    mapper.refine(cfg.refine_iters)
    return mapper.map
