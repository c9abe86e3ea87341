"""NVSM -> completion -> FEM for one object (thesis eq 14-18): :func:`verify_object`.

The per-episode wiring (detect -> lift -> object DB, then verification of the due entries) is
the agent's :class:`~splatsearch.agent.Perception` and :class:`~splatsearch.agent.Verifier`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from .inpainting import Inpainter, OpenCVInpainter, holes_from_alpha, split_holes
from .matching import (
    DEFAULT_TAU_M,
    Matcher,
    SIFTMatcher,
    best_view,
)
from .novel_views import composite_under, crop_box_for, hemisphere_viewpoints, render_novel_views


class NVSMResult(NamedTuple):
    """Result of :func:`verify_object`.

    Attributes:
        i_star: index of the best view (eq 18); e_max: its match count; counts: (V,) per view.
        matched: ``e_max >= tau_m``.
        viewmats: (V, 4, 4) the NVSM cameras; images: (V, H, W, 3) the completed views;
        holes: (V, H, W) bool, the pixels that were inpainted (for a cropped render, not the
            flat-filled background); rendered: (V, H, W, 3) the views before completion.
        alpha: (V, H, W) float32 accumulated opacity of the renders (after any fill), or None;
            what the local map covers from each camera (the look-again step reads its holes).
    """

    i_star: int
    e_max: int
    counts: np.ndarray
    matched: bool
    viewmats: np.ndarray
    images: np.ndarray
    holes: np.ndarray
    rendered: np.ndarray
    alpha: np.ndarray | None = None


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
        fill_crop: when :func:`verify_object` gets a ``fill_map``, render it with the same crop
            box as the object's map (True) or uncropped, the whole house (False).
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
    fill_crop: bool = True


def verify_object(goal: np.ndarray, gmap: Any, centroid: Sequence[float], K: np.ndarray, width: int, height: int, *,
                  matcher: Matcher | None = None, inpainter: Inpainter | None = None,
                  config: NVSMConfig | None = None, bbox: tuple | None = None,
                  viewmats: np.ndarray | None = None, fill_map: Any | None = None) -> NVSMResult:
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
        fill_map: optional second Gaussian map (e.g. the agent's online map of the whole house),
            rendered from the same cameras and composited under ``gmap``'s renders
            (:func:`~splatsearch.search.novel_views.composite_under`) before the holes are found,
            so that what ``gmap`` never covered (the object's surroundings up to the view's edge)
            shows the coarser map instead of a hole. ``config.fill_crop`` picks its crop.
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
    if fill_map is not None:
        f_rgb, f_alpha = render_novel_views(fill_map, vms, K, width, height, crop_box=box if cfg.fill_crop else None)
        rgb, alpha = composite_under(rgb, alpha, f_rgb, f_alpha)
    holes = holes_from_alpha(alpha, cfg.alpha_tau)
    # a learned multi-view completion (VCICN) was trained to fill every hole, background included,
    # from the views' cameras; a single-view fill gets only the enclosed gaps
    learned = cfg.inpaint and bool(getattr(inpainter, "completes_background", False))
    if box is not None and not learned:
        # around a cropped object the holes are mostly background that was cut away; inpainting
        # it would smear the object outwards, so it gets a flat colour and only enclosed gaps are
        # completed
        holes, outside = split_holes(holes)
        rgb[outside] = cfg.crop_fill
    if not cfg.inpaint:
        images = rgb
    elif getattr(inpainter, "wants_cameras", False):
        # the opacity lets a learned completion composite the soft covered pixels (VCICN "over")
        extra = {"alpha": alpha} if getattr(inpainter, "wants_alpha", False) else {}
        images = inpainter.inpaint(rgb, holes, viewmats=vms, **extra)
    else:
        images = inpainter.inpaint(rgb, holes)
    bv = best_view(goal, images, matcher)
    a = np.asarray(alpha, np.float32)
    if a.ndim == 4:
        a = a[..., 0]
    return NVSMResult(bv.i_star, bv.e_max, bv.counts, bool(bv.e_max >= cfg.tau_m), vms, images, holes, rgb, a)
