"""Object search: SOIM, NVSM, image completion and FEM (thesis Sections 4.2.2-4.2.5).

    detector = SimDetector()                                   # or UltralyticsDetector(path)
    search = ObjectSearch(env.K, 320, 240, detector, labels=[goal_class])
    search.observe(obs.frame.rgb, obs.frame.depth, obs.viewmat, mapper.map, frame=obs.frame)
    scores = search.verify_pending(goal_rgb, mapper.map)       # NVSM -> inpaint -> match (eq 18)
    search.db.matched()                                        # entries with e_max >= tau_m

Modules: ``detection`` (Detector, Detection, SimDetector, UltralyticsDetector), ``objects``
(mask lifting, ObjectDB of eq 13), ``novel_views`` (hemisphere cameras, map renders),
``inpainting`` (Inpainter, OpenCVInpainter, DiffusionInpainter), ``matching`` (Matcher,
SIFTMatcher, LoFTRMatcher, best_view of eq 18), ``appearance`` (AppearanceModel,
ColorHistogramAppearance, EncoderAppearance: a detection's colours against the goal object's),
``object_search`` (verify_object, ObjectSearch).
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
from .object_search import NVSMConfig, NVSMResult, ObjectSearch, verify_object
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
    "ObjectSearch",
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
