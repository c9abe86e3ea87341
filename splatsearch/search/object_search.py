"""The search loop's object side: detect -> lift -> object DB -> NVSM -> inpaint -> match.

:func:`verify_object` runs the NVSM, the completion and the FEM for one object (eq 18).
:class:`ObjectSearch` wires a detector, the object database and the verification together so an
agent calls :meth:`ObjectSearch.observe` every frame and :meth:`ObjectSearch.verify_pending`
when it wants the due NVSM runs done.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from .detection import Detection, Detector, check_detections
from .inpainting import Inpainter, OpenCVInpainter, holes_from_alpha, split_holes
from .matching import (
    DEFAULT_TAU_M,
    Matcher,
    SIFTMatcher,
    best_view,
)
from .novel_views import crop_box_for, hemisphere_viewpoints, render_novel_views
from .objects import (
    AddResult,
    LiftedObject,
    ObjectDB,
    lift_mask_depth,
    lift_mask_ids,
    map_top_ids,
)


class NVSMResult(NamedTuple):
    """Result of :func:`verify_object`.

    Attributes:
        i_star: index of the best view (eq 18); e_max: its match count; counts: (V,) per view.
        matched: ``e_max >= tau_m``.
        viewmats: (V, 4, 4) the NVSM cameras; images: (V, H, W, 3) the completed views;
        holes: (V, H, W) bool, the pixels that were inpainted (for a cropped render, not the
            flat-filled background); rendered: (V, H, W, 3) the views before completion.
    """

    i_star: int
    e_max: int
    counts: np.ndarray
    matched: bool
    viewmats: np.ndarray
    images: np.ndarray
    holes: np.ndarray
    rendered: np.ndarray


@dataclass
class NVSMConfig:
    """NVSM + completion + FEM settings.

    Attributes:
        radius: r_v in metres. n_views: N_R. elevations_deg: ring elevations.
        alpha_tau: render pixels with accumulated opacity below this are holes to inpaint.
        crop: render only the Gaussians in the object's box (see
            :func:`~splatsearch.search.novel_views.crop_box_for`); needs the entry's extent. Off
            by default, as in the thesis: on ground-truth renders the object's surroundings carry
            much of the same-instance evidence (textureless TVs matched only through their
            walls), and cropping lowered the goal instance's e_max more than the others'.
        crop_margin: metres added around the extent. floor_z: crop floor height (None keeps it).
        crop_fill: grey level given to the background cut away by the crop.
        tau_m: match threshold on e_max.
        inpaint: complete the holes before matching (False: match the raw renders, the thesis'
            "without inpainting" ablation).
    """

    radius: float = 1.5
    n_views: int = 12
    elevations_deg: tuple = (35.0,)
    alpha_tau: float = 0.5
    crop: bool = False
    crop_margin: float = 0.3
    floor_z: float | None = 0.05
    crop_fill: float = 0.5
    tau_m: float = DEFAULT_TAU_M
    inpaint: bool = True


def verify_object(goal: np.ndarray, gmap: Any, centroid: Sequence[float], K: np.ndarray, width: int, height: int, *,
                  matcher: Matcher | None = None, inpainter: Inpainter | None = None,
                  config: NVSMConfig | None = None, bbox: tuple | None = None,
                  viewmats: np.ndarray | None = None) -> NVSMResult:
    """Render the NVSM views of one object, complete them and match them to the goal image.

    Args:
        goal: (Hg, Wg, 3) goal image in [0, 1].
        gmap: the Gaussian map (or its ``render_args()`` tuple).
        centroid: (3,) object centroid in metres.
        K, width, height: the NVSM camera (intrinsics in pixels, image size).
        matcher, inpainter: defaults :class:`SIFTMatcher` (with the contrast threshold for renders,
            :data:`~splatsearch.search.matching.RENDER_CONTRAST_THRESHOLD`) /
            :class:`OpenCVInpainter`.
        config: :class:`NVSMConfig`.
        bbox: (min (3,), max (3,)) object extent in metres, used when ``config.crop``.
        viewmats: optional (V, 4, 4) cameras to use instead of ``config``'s hemisphere (e.g. the
            hemisphere cameras that :func:`~splatsearch.search.novel_views.clear_viewpoints` kept).
    """
    cfg = config or NVSMConfig()
    matcher = matcher or SIFTMatcher.for_renders()
    inpainter = inpainter or OpenCVInpainter()
    if viewmats is None:
        vms = hemisphere_viewpoints(centroid, cfg.radius, cfg.n_views, cfg.elevations_deg)
    else:
        vms = np.asarray(viewmats, np.float64)
        if vms.ndim != 3 or vms.shape[1:] != (4, 4) or len(vms) == 0:
            raise ValueError(f"viewmats must have shape (V, 4, 4) with V >= 1, got {vms.shape}")
    box = None
    if cfg.crop and bbox is not None:
        box = crop_box_for(bbox[0], bbox[1], cfg.crop_margin, cfg.floor_z)
    rgb, alpha = render_novel_views(gmap, vms, K, width, height, crop_box=box)
    holes = holes_from_alpha(alpha, cfg.alpha_tau)
    if box is not None:
        # around a cropped object the holes are mostly background that was cut away; inpainting
        # it would smear the object outwards, so it gets a flat colour and only enclosed gaps are
        # completed
        holes, outside = split_holes(holes)
        rgb[outside] = cfg.crop_fill
    images = inpainter.inpaint(rgb, holes) if cfg.inpaint else rgb
    bv = best_view(goal, images, matcher)
    return NVSMResult(bv.i_star, bv.e_max, bv.counts, bool(bv.e_max >= cfg.tau_m), vms, images, holes, rgb)


class ObjectSearch:
    """Detector + lifting + object DB + NVSM verification, for one episode.

    Args:
        K, width, height: the robot camera.
        detector: any :class:`Detector`.
        labels: detection labels to track (e.g. just the goal class); None tracks all.
        db: the object database (default :class:`ObjectDB` with its defaults).
        matcher, inpainter, nvsm: verification settings (see :func:`verify_object`; the default
            matcher is SIFT with the contrast threshold for renders).
        erode_px: mask erosion before lifting.
    """

    def __init__(self, K: np.ndarray, width: int, height: int, detector: Detector, *,
                 labels: Sequence[str] | None = None, db: ObjectDB | None = None, matcher: Matcher | None = None,
                 inpainter: Inpainter | None = None, nvsm: NVSMConfig | None = None, erode_px: int = 2):
        self.K = np.asarray(K, np.float32)
        if self.K.shape != (3, 3):
            raise ValueError(f"K must be (3, 3), got {self.K.shape}")
        self.width, self.height = int(width), int(height)
        self.detector = detector
        self.labels = None if labels is None else set(labels)
        self.db = db if db is not None else ObjectDB()
        self.matcher = matcher or SIFTMatcher.for_renders()
        self.inpainter = inpainter or OpenCVInpainter()
        self.nvsm = nvsm or NVSMConfig()
        self.erode_px = int(erode_px)

    def lift(self, det: Detection, depth: np.ndarray, viewmat: np.ndarray, top_ids: np.ndarray | None = None,
             means: np.ndarray | None = None, active: np.ndarray | None = None) -> LiftedObject | None:
        """Lift one detection: through the Gaussian ids when given, else (or if that finds too few
        Gaussians) from the masked depth."""
        lifted = None
        if top_ids is not None and means is not None:
            lifted = lift_mask_ids(det.mask, top_ids, means, active=active, erode_px=self.erode_px)
        if lifted is None:
            lifted = lift_mask_depth(det.mask, depth, viewmat, self.K, erode_px=self.erode_px)
        return lifted

    def observe(self, rgb: np.ndarray, depth: np.ndarray, viewmat: np.ndarray, gmap: Any = None,
                frame: Any = None) -> list[tuple[Detection, AddResult]]:
        """Detect, lift and merge the objects of one frame.

        rgb (H, W, 3) in [0, 1]; depth (H, W) metres; viewmat (4, 4) the camera (the pose the map
        was updated with); gmap the current :class:`~splatsearch.gaussians.GaussianMap` (None: lift
        from depth); frame: passed to the detector (the simulator frame for :class:`SimDetector`).
        Returns (detection, :class:`AddResult`) per merged detection.
        """
        rgb, depth = np.asarray(rgb), np.asarray(depth)
        if rgb.shape != (self.height, self.width, 3) or depth.shape != (self.height, self.width):
            raise ValueError(f"expected rgb ({self.height}, {self.width}, 3) and depth ({self.height}, {self.width}); "
                             f"got {rgb.shape}, {depth.shape}")
        dets = check_detections(self.detector.detect(rgb, frame), rgb.shape[:2], type(self.detector).__name__)
        dets = [d for d in dets if self.labels is None or d.label in self.labels]
        if not dets:
            return []
        top_ids = means = active = None
        if gmap is not None and gmap.n_active > 0:
            top_ids = map_top_ids(gmap, viewmat, self.K, self.width, self.height)
            means, active = np.asarray(gmap.means), np.asarray(gmap.active)
        out = []
        for d in dets:
            lifted = self.lift(d, depth, viewmat, top_ids, means, active)
            if lifted is not None:
                out.append((d, self.db.add_lifted(d.label, lifted, viewmat)))
        return out

    def verify(self, entry_id: int, goal: np.ndarray, gmap: Any) -> NVSMResult:
        """Run :func:`verify_object` for one entry now and record the result in the DB."""
        e = self.db[entry_id]
        bbox = None if e.bbox_min is None else (e.bbox_min, e.bbox_max)
        score = verify_object(goal, gmap, e.centroid, self.K, self.width, self.height, matcher=self.matcher,
                              inpainter=self.inpainter, config=self.nvsm, bbox=bbox)
        self.db.record_match(entry_id, score.e_max, score.i_star, self.nvsm.tau_m, score.viewmats[score.i_star])
        return score

    def verify_pending(self, goal: np.ndarray, gmap: Any) -> dict[int, NVSMResult]:
        """Verify every entry whose NVSM is due (see :meth:`ObjectDB.pop_pending`)."""
        return {i: self.verify(i, goal, gmap) for i in self.db.pop_pending()}
