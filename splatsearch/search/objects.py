"""Lifting detection masks to 3-D and the object database of eq 13 (thesis Section 4.2.2).

Lifting: the pixels of a mask are mapped to the Gaussians that dominate them (the per-pixel
top-contributor map of :func:`splatsearch.rasterize_top_ids`); the object's Gaussians are the
unique ids under the mask and its centroid is the mean of their means. Without a top-id map
(no map yet, or another front end) the masked depth is back-projected instead.

Object database: entries ``O = {G, mu, V}`` (eq 13) plus the search state the planner needs
(best match score ``e_max``, best novel view, matched flag). A new observation merges into the
nearest entry of the same label within ``tau_d`` (incremental mean of centroids), else it opens a
new entry. The NVSM runs for an entry each time its number of distinct viewpoints reaches a
multiple of ``f_O``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from splatsearch.camera import pixels_to_world

from .novel_views import camera_pose

# --------------------------------------------------------------------------------------------
# lifting
# --------------------------------------------------------------------------------------------


class LiftedObject(NamedTuple):
    """A mask lifted to 3-D.

    Attributes:
        centroid: (3,) world position in metres.
        bbox_min, bbox_max: (3,) robust world extent (5th / 95th percentiles) in metres.
        points: (M, 3) the 3-D points behind the mask (Gaussian means or back-projected pixels).
        gaussian_ids: (M,) int rows of the map's arrays (capacity rows), or None for a depth lift.
    """

    centroid: np.ndarray
    bbox_min: np.ndarray
    bbox_max: np.ndarray
    points: np.ndarray
    gaussian_ids: np.ndarray | None


def _check_mask(mask, shape=None) -> np.ndarray:
    mask = np.asarray(mask)
    if mask.ndim != 2 or mask.dtype != bool:
        raise ValueError(f"mask must be a 2-D bool array, got {mask.dtype} {mask.shape}")
    if shape is not None and mask.shape != tuple(shape):
        raise ValueError(f"mask {mask.shape} does not match the image size {tuple(shape)}")
    return mask


def erode_mask(mask: np.ndarray, px: int) -> np.ndarray:
    """``mask`` eroded by ``px`` pixels (square structuring element); ``px`` = 0 returns it."""
    mask = _check_mask(mask)
    if px < 0:
        raise ValueError(f"erosion must be >= 0 pixels, got {px}")
    if px == 0:
        return mask
    import cv2

    k = np.ones((2 * px + 1, 2 * px + 1), np.uint8)
    return cv2.erode(mask.astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)


def _summarise(points: np.ndarray, ids, trim: float | None) -> LiftedObject | None:
    if len(points) == 0:
        return None
    if trim is not None and len(points) >= 8:
        # A few mask pixels at depth discontinuities still hit background Gaussians metres behind
        # the object; drop points far from the median (robust scale, with a floor so a compact
        # object keeps its whole extent).
        med = np.median(points, 0)
        d = np.linalg.norm(points - med, axis=1)
        scale = max(1.4826 * float(np.median(np.abs(d - np.median(d)))), 0.05)
        keep = d <= np.median(d) + trim * scale
        points = points[keep]
        ids = None if ids is None else ids[keep]
    lo, hi = np.percentile(points, [5, 95], axis=0)
    return LiftedObject(points.mean(0), lo, hi, points, ids)


def lift_mask_ids(mask: np.ndarray, top_ids: np.ndarray, means: np.ndarray, *, active: np.ndarray | None = None,
                  erode_px: int = 2, trim: float | None = 3.0, min_gaussians: int = 3) -> LiftedObject | None:
    """The Gaussians under a mask and their centroid.

    Args:
        mask: (H, W) bool detection mask.
        top_ids: (H, W) int per-pixel index of the dominant Gaussian, -1 for none (from
            :func:`splatsearch.rasterize_top_ids` at the detection's camera).
        means: (C, 3) the map's Gaussian means in metres (the same rows ``top_ids`` indexes).
        active: optional (C,) bool; ids of inactive rows are ignored.
        erode_px: erode the mask first so boundary pixels, whose top Gaussian is often the
            background, do not bleed in; skipped if it would leave no pixel.
        trim: drop points more than ``trim`` robust deviations from the median (None: keep all).
        min_gaussians: fewer distinct Gaussians than this gives None (too little to localise).

    Returns:
        :class:`LiftedObject`, or None if the mask covers too few mapped Gaussians.
    """
    top_ids = np.asarray(top_ids)
    if top_ids.ndim != 2 or not np.issubdtype(top_ids.dtype, np.integer):
        raise ValueError(f"top_ids must be a 2-D integer array, got {top_ids.dtype} {top_ids.shape}")
    mask = _check_mask(mask, top_ids.shape)
    means = np.asarray(means, np.float64)
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"means must have shape (C, 3), got {means.shape}")
    if top_ids.size and top_ids.max(initial=-1) >= len(means):
        raise ValueError(f"top_ids index row {int(top_ids.max())} but means has only {len(means)} rows")
    m = erode_mask(mask, erode_px)
    if not m.any():
        m = mask
    ids = np.unique(top_ids[m])
    ids = ids[ids >= 0]
    if active is not None:
        active = np.asarray(active, bool).reshape(-1)
        if active.shape != (len(means),):
            raise ValueError(f"active must have shape ({len(means)},), got {active.shape}")
        ids = ids[active[ids]]
    if len(ids) < max(1, int(min_gaussians)):
        return None
    return _summarise(means[ids], ids, trim)


def backproject_mask(mask: np.ndarray, depth: np.ndarray, viewmat: np.ndarray, K: np.ndarray,
                     erode_px: int = 2) -> np.ndarray:
    """World points (M, 3) in metres of the masked pixels with valid depth (> 0).

    depth (H, W) metres; viewmat (4, 4) world-to-camera (OpenCV); K (3, 3) pixels.
    """
    depth = np.asarray(depth, np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth must have shape (H, W), got {depth.shape}")
    mask = _check_mask(mask, depth.shape)
    m = erode_mask(mask, erode_px)
    if not (m & (depth > 0)).any():
        m = mask
    v, u = np.nonzero(m & (depth > 0) & np.isfinite(depth))
    return pixels_to_world(u, v, depth[v, u], viewmat, K)


def lift_mask_depth(mask: np.ndarray, depth: np.ndarray, viewmat: np.ndarray, K: np.ndarray, *, erode_px: int = 2,
                    trim: float | None = 3.0, min_pixels: int = 10) -> LiftedObject | None:
    """Fallback lift without Gaussian ids: back-project the masked depth (see
    :func:`backproject_mask`) and summarise it like :func:`lift_mask_ids`. The centroid is the mean
    of the trimmed points (the trim makes it robust, like a median, to depth-edge outliers).
    Returns None with fewer than ``min_pixels`` valid pixels."""
    pts = backproject_mask(mask, depth, viewmat, K, erode_px)
    if len(pts) < max(1, int(min_pixels)):
        return None
    return _summarise(pts, None, trim)


def map_top_ids(gmap: Any, viewmat: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) int32 top-contributor Gaussian ids of a :class:`~splatsearch.gaussians.GaussianMap`
    (capacity rows; -1 = none) at ``viewmat``, via :func:`splatsearch.rasterize_top_ids`."""
    from splatsearch.rasterization import rasterize_top_ids

    means, quats, scales, opac, _ = gmap.render_args()
    return rasterize_top_ids(np.asarray(means), np.asarray(quats), np.asarray(scales), np.asarray(opac), viewmat, K,
                             width, height)


# --------------------------------------------------------------------------------------------
# object database (eq 13)
# --------------------------------------------------------------------------------------------

@dataclass
class ObjectEntry:
    """One object of the database (eq 13 plus search state).

    Attributes:
        id: stable entry id (0, 1, ... in creation order).
        label: class label.
        centroid: (3,) metres, incremental mean over merged observations.
        n_obs: observations merged so far.
        viewpoints: the set of quantised viewpoint keys it was seen from (see
            :meth:`ObjectDB.viewpoint_key`).
        bbox_min, bbox_max: (3,) metres, incremental mean of the observations' robust extents.
        gaussian_ids: map rows of the latest id-based lift (G in eq 13). Rows are renumbered when
            the mapper compacts, so they describe the map at that observation only.
        e_max: best feature-match count over the NVSM runs so far (-1: never evaluated).
        best_view: index of the best novel view of the run that set ``e_max`` (-1: none).
        best_viewmat: (4, 4) world-to-camera of that view, or None.
        matched: ``e_max >= tau_m``.
        n_nvsm: NVSM runs done for it.
        colour_sum, colour_weight, colour_views: the weighted sum and total weight of its colour
            similarities to the goal object, over ``colour_views`` detections (see
            :meth:`ObjectDB.record_colour` and :attr:`colour_similarity`).
    """

    id: int
    label: str
    centroid: np.ndarray
    n_obs: int = 1
    viewpoints: set = field(default_factory=set)
    bbox_min: np.ndarray | None = None
    bbox_max: np.ndarray | None = None
    gaussian_ids: np.ndarray | None = None
    e_max: float = -1.0
    best_view: int = -1
    best_viewmat: np.ndarray | None = None
    matched: bool = False
    n_nvsm: int = 0
    colour_sum: float = 0.0
    colour_weight: float = 0.0
    colour_views: int = 0

    @property
    def colour_similarity(self) -> float:
        """Weighted mean colour similarity to the goal object in [0, 1] (-1: none yet)."""
        return self.colour_sum / self.colour_weight if self.colour_weight > 0 else -1.0

    @property
    def extent_radius(self) -> float:
        """Half the diagonal of the mean extent box in metres (0 without one)."""
        if self.bbox_min is None:
            return 0.0
        return float(0.5 * np.linalg.norm(self.bbox_max - self.bbox_min))


class AddResult(NamedTuple):
    """Outcome of :meth:`ObjectDB.add`: the entry id, whether it was created, whether the viewpoint
    was new for it, and whether the NVSM should run for it now."""

    entry_id: int
    created: bool
    new_viewpoint: bool
    trigger_nvsm: bool


class ObjectDB:
    """Object database D_O (eq 13) with merging and the NVSM trigger.

    Args:
        tau_d: merge distance in metres between centroids of the same label. A lifted centroid
            is the mean of the *visible* surface, so it moves by up to about half the object's
            size between opposite sides; separate same-class objects are mostly further apart
            (``docs/results.md``).
        f_O: run the NVSM when an entry's distinct-viewpoint count is a multiple of f_O.
        pos_cell: viewpoint quantisation of the camera position (x, y) in metres.
        yaw_bin_deg: viewpoint quantisation of the camera heading in degrees.

    Viewpoints are quantised so that jitter or standing still does not count as new evidence:
    a viewpoint key is (floor(x / pos_cell), floor(y / pos_cell), round(yaw / yaw_bin) mod bins).
    With the Habitat action set (0.25 m steps, 30 deg turns) the defaults (0.5 m cells, 30 deg
    bins) make two forward steps or one turn a new viewpoint.
    """

    def __init__(self, tau_d: float = 1.0, f_O: int = 3, pos_cell: float = 0.5, yaw_bin_deg: float = 30.0):
        if not (np.isfinite(tau_d) and tau_d > 0):
            raise ValueError(f"tau_d must be a positive distance in metres, got {tau_d}")
        if isinstance(f_O, bool) or int(f_O) != f_O or f_O < 1:
            raise ValueError(f"f_O must be an integer >= 1, got {f_O}")
        if not (pos_cell > 0 and 0 < yaw_bin_deg <= 360):
            raise ValueError(f"need pos_cell > 0 and 0 < yaw_bin_deg <= 360, got {pos_cell}, {yaw_bin_deg}")
        self.tau_d, self.f_O = float(tau_d), int(f_O)
        self.pos_cell, self.yaw_bin = float(pos_cell), float(np.radians(yaw_bin_deg))
        self.entries: list[ObjectEntry] = []
        self._pending: list[int] = []

    def __len__(self) -> int:
        return len(self.entries)

    def __iter__(self):
        return iter(self.entries)

    def __getitem__(self, entry_id: int) -> ObjectEntry:
        return self.entries[entry_id]

    # -- viewpoints ---------------------------------------------------------------------------
    def viewpoint_key(self, pose: np.ndarray) -> tuple[int, int, int]:
        """Quantised viewpoint of a camera pose: ``pose`` is (x, y, yaw) (metres, radians, yaw about
        +z from +x) or a (4, 4) world-to-camera viewmat (position = camera centre, yaw = heading of
        the optical axis projected on the floor)."""
        p = np.asarray(pose, np.float64)
        if p.shape == (4, 4):
            c, fwd = camera_pose(p)
            x, y, yaw = c[0], c[1], np.arctan2(fwd[1], fwd[0])
        elif p.shape == (3,):
            x, y, yaw = p
        else:
            raise ValueError(f"viewpoint pose must be (x, y, yaw) or a (4, 4) viewmat, got shape {p.shape}")
        if not np.all(np.isfinite(p)):
            raise ValueError("viewpoint pose contains NaN or Inf")
        n_bins = max(1, round(2 * np.pi / self.yaw_bin))
        return (int(np.floor(x / self.pos_cell)), int(np.floor(y / self.pos_cell)),
                int(np.round(yaw / self.yaw_bin)) % n_bins)

    # -- updates ------------------------------------------------------------------------------
    def add(self, label: str, centroid: np.ndarray, viewpoint_pose: np.ndarray, *, bbox: tuple | None = None,
            gaussian_ids: np.ndarray | None = None) -> AddResult:
        """Merge one lifted observation.

        Args:
            label: class label of the detection.
            centroid: (3,) world position in metres.
            viewpoint_pose: the observing camera, (x, y, yaw) or a (4, 4) viewmat.
            bbox: optional (bbox_min (3,), bbox_max (3,)) robust extent in metres.
            gaussian_ids: optional map rows of the object (G in eq 13).

        Returns:
            :class:`AddResult`. When ``trigger_nvsm`` is True the id is also queued (see
            :meth:`pop_pending`).
        """
        if not isinstance(label, str) or not label:
            raise ValueError(f"label must be a non-empty string, got {label!r}")
        c = np.asarray(centroid, np.float64).reshape(-1)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise ValueError(f"centroid must be a finite (3,) position, got {np.asarray(centroid)}")
        key = self.viewpoint_key(viewpoint_pose)
        if bbox is not None:
            lo, hi = (np.asarray(b, np.float64).reshape(3) for b in bbox)
            if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo <= hi)):
                raise ValueError("bbox must be finite (min (3,), max (3,)) with min <= max")
        best, best_d = None, self.tau_d
        for e in self.entries:
            if e.label != label:
                continue
            d = float(np.linalg.norm(e.centroid - c))
            if d < best_d:
                best, best_d = e, d
        created = best is None
        if created:
            best = ObjectEntry(len(self.entries), label, c.copy())
            if bbox is not None:
                best.bbox_min, best.bbox_max = lo.copy(), hi.copy()
            self.entries.append(best)
        else:
            n = best.n_obs
            best.centroid = (n * best.centroid + c) / (n + 1)
            if bbox is not None:
                if best.bbox_min is None:
                    best.bbox_min, best.bbox_max = lo.copy(), hi.copy()
                else:
                    best.bbox_min = (n * best.bbox_min + lo) / (n + 1)
                    best.bbox_max = (n * best.bbox_max + hi) / (n + 1)
            best.n_obs = n + 1
        if gaussian_ids is not None:
            best.gaussian_ids = np.asarray(gaussian_ids).copy()
        new_vp = key not in best.viewpoints
        best.viewpoints.add(key)
        trigger = new_vp and len(best.viewpoints) % self.f_O == 0
        if trigger and best.id not in self._pending:
            self._pending.append(best.id)
        return AddResult(best.id, created, new_vp, trigger)

    def add_lifted(self, label: str, lifted: LiftedObject, viewpoint_pose: np.ndarray) -> AddResult:
        """:meth:`add` for a :class:`LiftedObject`."""
        return self.add(label, lifted.centroid, viewpoint_pose, bbox=(lifted.bbox_min, lifted.bbox_max),
                        gaussian_ids=lifted.gaussian_ids)

    def pop_pending(self) -> list[int]:
        """Entry ids whose NVSM is due, in trigger order; clears the queue."""
        out, self._pending = self._pending, []
        return out

    def record_match(self, entry_id: int, e_max: float, best_view: int, tau_m: float,
                     best_viewmat: np.ndarray | None = None, *, nvsm_run: bool = True) -> ObjectEntry:
        """Store an NVSM + FEM result (eq 18). ``e_max`` keeps the best score over runs, since every
        run is evidence for the same object; ``matched`` becomes ``e_max >= tau_m``.
        ``nvsm_run=False`` records a match of a real observation, which does not count as an NVSM
        run (``n_nvsm``)."""
        e = self.entries[entry_id]
        if not np.isfinite(e_max) or e_max < 0:
            raise ValueError(f"e_max must be a finite count >= 0, got {e_max}")
        e.n_nvsm += int(bool(nvsm_run))
        if e_max > e.e_max:
            e.e_max, e.best_view = float(e_max), int(best_view)
            e.best_viewmat = None if best_viewmat is None else np.asarray(best_viewmat, np.float64).copy()
        e.matched = e.e_max >= tau_m
        return e

    def record_colour(self, entry_id: int, similarity: float, weight: float = 1.0) -> ObjectEntry:
        """Add one detection's colour similarity to the goal object (in [0, 1]) with a weight
        > 0 (larger masks are more reliable); the entry keeps the weighted mean."""
        e = self.entries[entry_id]
        if not (np.isfinite(similarity) and 0.0 <= similarity <= 1.0):
            raise ValueError(f"similarity must be in [0, 1], got {similarity}")
        if not (np.isfinite(weight) and weight > 0):
            raise ValueError(f"weight must be > 0, got {weight}")
        e.colour_sum += float(similarity) * float(weight)
        e.colour_weight += float(weight)
        e.colour_views += 1
        return e

    # -- queries ------------------------------------------------------------------------------
    def matched(self) -> list[ObjectEntry]:
        """Entries declared to be the goal, best score first."""
        return sorted((e for e in self.entries if e.matched), key=lambda e: -e.e_max)

    def scores(self) -> tuple[np.ndarray, np.ndarray]:
        """(centroids (M, 3) metres, e_max (M,) with unevaluated entries as 0) for the planner's eq 20."""
        if not self.entries:
            return np.zeros((0, 3)), np.zeros(0)
        return (np.stack([e.centroid for e in self.entries]),
                np.array([max(e.e_max, 0.0) for e in self.entries]))
