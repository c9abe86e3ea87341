"""Object search: SOIM, NVSM, image completion and FEM (thesis Sections 4.2.2-4.2.5).

    dets = SimDetector().detect(rgb, frame)                    # or UltralyticsDetector(path)
    ids = map_top_ids(gmap, viewmat, K, W, H)                  # per-pixel top Gaussian
    lifted = lift_mask_ids(dets[0].mask, ids, gmap.means)      # -> LiftedObject (centroid, box)
    db = ObjectDB(); db.add_lifted(dets[0].label, lifted, viewmat)        # eq 13
    score = verify_object(goal_rgb, gmap, lifted.centroid, K, W, H)       # NVSM -> inpaint -> match (eq 18)

The agent (:mod:`splatsearch.agent`) runs these per frame in its ``Perception`` and ``Verifier``.

Modules: ``detection`` (Detector, Detection, SimDetector, UltralyticsDetector), ``objects``
(mask lifting, ObjectDB of eq 13), ``novel_views`` (hemisphere cameras, map renders),
``inpainting`` (Inpainter, OpenCVInpainter, DiffusionInpainter), ``matching`` (Matcher,
SIFTMatcher, LoFTRMatcher, best_view of eq 18), ``appearance`` (AppearanceModel,
ColorHistogramAppearance, EncoderAppearance: a detection's colours against the goal object's),
``object_search`` (verify_object, NVSMConfig, NVSMResult).
"""

from .appearance import (
    AppearanceModel,
    ColorHistogramAppearance,
    EncoderAppearance,
    goal_object_mask,
)
from .detection import (
    COCO_TO_GOAL,
    Detection,
    Detector,
    SimDetector,
    UltralyticsDetector,
    check_detections,
)
from .inpainting import (
    DiffusionInpainter,
    Inpainter,
    OpenCVInpainter,
    holes_from_alpha,
    split_holes,
)
from .matching import (
    DEFAULT_TAU_M,
    RENDER_CONTRAST_THRESHOLD,
    RENDER_TAU_M,
    BestView,
    LoFTRMatcher,
    Matcher,
    SIFTMatcher,
    best_view,
    ransac_inliers,
)
from .novel_views import crop_box_for, hemisphere_viewpoints, render_novel_views
from .object_search import NVSMConfig, NVSMResult, verify_object
from .objects import (
    AddResult,
    LiftedObject,
    ObjectDB,
    ObjectEntry,
    backproject_mask,
    erode_mask,
    lift_mask_depth,
    lift_mask_ids,
    map_top_ids,
)

__all__ = [
    "COCO_TO_GOAL",
    "DEFAULT_TAU_M",
    "RENDER_CONTRAST_THRESHOLD",
    "RENDER_TAU_M",
    "AddResult",
    "AppearanceModel",
    "BestView",
    "ColorHistogramAppearance",
    "Detection",
    "Detector",
    "DiffusionInpainter",
    "EncoderAppearance",
    "Inpainter",
    "LiftedObject",
    "LoFTRMatcher",
    "Matcher",
    "NVSMConfig",
    "NVSMResult",
    "ObjectDB",
    "ObjectEntry",
    "OpenCVInpainter",
    "SIFTMatcher",
    "SimDetector",
    "UltralyticsDetector",
    "backproject_mask",
    "best_view",
    "check_detections",
    "crop_box_for",
    "erode_mask",
    "goal_object_mask",
    "hemisphere_viewpoints",
    "holes_from_alpha",
    "lift_mask_depth",
    "lift_mask_ids",
    "map_top_ids",
    "ransac_inliers",
    "render_novel_views",
    "split_holes",
    "verify_object",
]
