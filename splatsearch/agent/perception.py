"""Perception: the online map and the objects seen in it (thesis Sections 4.2.1-4.2.2).

Per frame: map it (every ``map_every``-th frame, at the mapping resolution), detect goal-class
objects, lift each mask onto the Gaussians that render it (or onto the masked depth), merge it
into the object DB (eq 13), keep the observation for the object's local map, and score the
detection's colours against the goal object's (the colour cue). Nothing here decides whether an
object is the goal; :mod:`splatsearch.agent.verification` does.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import NamedTuple

import cv2
import numpy as np

from splatsearch.mapper import Mapper, MapperConfig
from splatsearch.nav.encoders import ImageEncoder, cosine
from splatsearch.search.appearance import AppearanceModel, goal_object_mask
from splatsearch.search.detection import Detection, Detector, check_detections
from splatsearch.search.local_map import ObservationStore
from splatsearch.search.objects import ObjectDB, lift_mask_depth, lift_mask_ids, map_top_ids

from .config import AgentConfig

#: metres between the Gaussian-id lift of a detection and its depth lift beyond which the depth
#: lift is used (the coarse online map has not resolved the object yet)
LIFT_TOLERANCE = 0.5


class NewView(NamedTuple):
    """A detection that gave object entry ``entry_id`` a new viewpoint."""

    entry_id: int
    detection: Detection


class Perception:
    """The online Gaussian map, the object DB and the per-object evidence that perception gives.

    Args:
        K (3, 3), width, height: the robot camera (pixels).
        goal: (H, W, 3) float32 goal image in [0, 1]; goal_class: the goal category.
        config: :class:`AgentConfig` (mapping and DB settings).
        detector, encoder, colour_model: the plug-ins.
        colour_cue: compare detections' colours with the goal object's; needs the goal object's
            mask: ``goal_mask`` (H, W) bool, or else the detector run on the goal image
            (``goal_frame`` goes to it). Without a mask the cue is off (:attr:`goal_signature`
            is None).

    State: :attr:`mapper` (the online map), :attr:`db` (:class:`ObjectDB`), :attr:`observations`
    (full-resolution RGB-D per entry, for the local maps), :attr:`crop_cosine` (entry id -> best
    encoder cosine between a crop around one of its detections and the goal image; only a
    tie-break of the fallback choice).
    """

    def __init__(self, K: np.ndarray, width: int, height: int, goal: np.ndarray, goal_class: str,
                 config: AgentConfig, *, detector: Detector, encoder: ImageEncoder, colour_model: AppearanceModel,
                 colour_cue: bool, goal_mask: np.ndarray | None = None, goal_frame=None):
        cfg = self.cfg = config
        self.K = np.asarray(K, np.float64)
        self.W, self.H = int(width), int(height)
        self.goal, self.goal_class = goal, goal_class
        self.detector, self.encoder, self.colour_model = detector, encoder, colour_model
        self.goal_embedding = np.asarray(encoder.embed(goal), np.float32)
        self.goal_signature = self._goal_signature(goal_mask, goal_frame) if colour_cue else None
        # the mapping camera: the robot camera scaled down
        s = cfg.map_scale
        self.mW, self.mH = max(8, round(self.W * s)), max(8, round(self.H * s))
        self.mK = self.K.copy()
        self.mK[:2] *= np.array([[self.mW / self.W], [self.mH / self.H]])
        self.mapper = Mapper(self.mK.astype(np.float32), self.mW, self.mH,
                             MapperConfig(iters=cfg.map_iters, stride=cfg.map_stride, seed=cfg.seed))
        self.db = ObjectDB(tau_d=cfg.tau_d, f_O=cfg.f_O)
        self.observations = ObservationStore(cfg.local_map.max_frames, cfg.local_map.min_separation)
        self.crop_cosine: dict[int, float] = {}

    def _goal_signature(self, goal_mask, goal_frame) -> np.ndarray | None:
        if goal_mask is None:
            try:
                dets = self.detector.detect(self.goal, goal_frame)
            except ValueError:
                dets = []  # e.g. the simulator detector without the goal image's frame
            dets = check_detections(dets, self.goal.shape[:2], type(self.detector).__name__)
            goal_mask = goal_object_mask(dets, self.goal_class)
        if goal_mask is None:
            return None
        goal_mask = np.asarray(goal_mask, bool)
        if goal_mask.shape != self.goal.shape[:2]:
            raise ValueError(f"goal_mask shape {goal_mask.shape} does not match the goal image {self.goal.shape[:2]}")
        if goal_mask.sum() < 1:
            return None
        return self.colour_model.signature(self.goal, goal_mask)

    def map_frame(self, rgb: np.ndarray, depth: np.ndarray, viewmat: np.ndarray) -> None:
        """Add one frame to the online map at the mapping resolution: rgb (H, W, 3), depth (H, W)
        metres, viewmat (4, 4) world-to-camera."""
        small_rgb = cv2.resize(np.asarray(rgb, np.float32), (self.mW, self.mH), interpolation=cv2.INTER_AREA)
        small_d = cv2.resize(np.asarray(depth, np.float32), (self.mW, self.mH), interpolation=cv2.INTER_NEAREST)
        self.mapper.update(small_rgb, small_d, viewmat)

    def detect(self, rgb: np.ndarray, frame=None) -> list[Detection]:
        """The detector's goal-class detections in ``rgb``, checked (a plug-in's mistake is reported
        here, naming it, rather than deep in the lifting)."""
        dets = check_detections(self.detector.detect(rgb, frame), np.shape(rgb)[:2], type(self.detector).__name__)
        return [d for d in dets if d.label == self.goal_class]

    def observe(self, rgb: np.ndarray, depth: np.ndarray, viewmat: np.ndarray, frame=None, *,
                use_map: bool = True) -> Iterator[NewView]:
        """Detect, lift and merge the goal-class objects of one frame; yields each detection that
        gave its entry a new viewpoint, after recording its colours and observation.

        A generator: a detection is merged only after the caller has handled the one before it,
        so what the caller records for one (a feature-match count) is in the DB when the next is
        merged. ``use_map``: lift through the online map's top-contributor ids (the frame was
        just mapped); otherwise, and wherever they disagree with it by more than
        :data:`LIFT_TOLERANCE`, the masked depth places the detection.
        """
        if np.shape(rgb) != (self.H, self.W, 3) or np.shape(depth) != (self.H, self.W):
            raise ValueError(f"expected rgb ({self.H}, {self.W}, 3) and depth ({self.H}, {self.W}); "
                             f"got {np.shape(rgb)}, {np.shape(depth)}")
        dets = self.detect(rgb, frame)
        ids = None
        for d in dets:
            if np.mean(depth[d.mask] > 0) < 0.5:
                # mostly beyond the depth sensor's range: the map holds no Gaussians of it, and
                # those under its mask belong to whatever nearer thing frames it
                continue
            lifted = None
            if use_map:
                if ids is None:
                    ids = map_top_ids(self.mapper.map, viewmat, self.mK, self.mW, self.mH)
                mask = cv2.resize(d.mask.astype(np.uint8), (self.mW, self.mH), interpolation=cv2.INTER_NEAREST) > 0
                lifted = lift_mask_ids(mask, ids, np.asarray(self.mapper.map.means),
                                       active=np.asarray(self.mapper.map.active), erode_px=1)
            by_depth = lift_mask_depth(d.mask, depth, viewmat, self.K, erode_px=1)
            if lifted is None or (by_depth is not None and
                                  np.linalg.norm(lifted.centroid - by_depth.centroid) > LIFT_TOLERANCE):
                # too few Gaussians under a small mask at the mapping resolution, or Gaussians of
                # what lies behind the object: the full-resolution masked depth places it instead
                lifted = by_depth
            if lifted is None:
                continue
            res = self.db.add_lifted(d.label, lifted, viewmat)
            if not res.new_viewpoint:
                continue
            sim = cosine(self.encoder.embed(crop_around(rgb, d.mask)), self.goal_embedding)
            self.crop_cosine[res.entry_id] = max(sim, self.crop_cosine.get(res.entry_id, -1.0))
            if self.goal_signature is not None:
                a = self.colour_model.similarity(self.goal_signature, self.colour_model.signature(rgb, d.mask))
                w = min(d.n_pixels, self.cfg.colour_full_px) / self.cfg.colour_full_px
                self.db.record_colour(res.entry_id, min(max(a, 0.0), 1.0), w)
            self.observations.add(res.entry_id, rgb, depth, viewmat)
            yield NewView(res.entry_id, d)


def crop_around(rgb: np.ndarray, mask: np.ndarray, margin: float = 0.5, min_size: int = 32) -> np.ndarray:
    """The region of rgb (H, W, 3) around the bounding box of mask (H, W) bool, grown by
    ``margin`` of its size each side and to at least ``min_size`` px a side (a sliver of a mask
    still gives the matcher a patch); the whole image for an empty mask."""
    rows, cols = np.nonzero(mask)
    if len(rows) == 0:
        return rgb
    H, W = mask.shape
    r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    dr = max(int((r1 - r0) * margin), (min_size - (r1 - r0) + 1) // 2)
    dc = max(int((c1 - c0) * margin), (min_size - (c1 - c0) + 1) // 2)
    return rgb[max(0, r0 - dr):min(H, r1 + dr), max(0, c0 - dc):min(W, c1 + dc)]
