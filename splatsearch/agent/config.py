"""The agent's settings and the variant, resolved once into explicit switches.

:class:`AgentConfig` holds every number a user may change; :func:`resolve_variant` turns its
``variant`` (a row of the thesis' Table IV) into a :class:`Strategy` of booleans when the agent is
built. Nothing after construction compares the variant string.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from splatsearch.search.local_map import LocalMapConfig
from splatsearch.search.matching import DEFAULT_TAU_M, RENDER_TAU_M

from .variants import VARIANTS, canonical_variant


@dataclass(frozen=True)
class Strategy:
    """A variant spelled out: what the agent does, as switches read by the three rooms.

    Attributes:
        frontier_terms: eq 19 uses the object term E (beta) and the value term V (delta);
            False leaves the distance term alone (``nearest_frontier``, ``gaussnav``).
        nvsm_during_search: run an object's NVSM as soon as it is due (every ``f_O`` new
            viewpoints); False for ``no_nvsm`` (never) and ``gaussnav`` (after exploring).
        identify_after_exploring: take nothing for the goal before the house is explored, then
            run the NVSM of every object not yet verified (``gaussnav``).
        match_observations: match the real camera crop around each new detection against the goal
            image (``no_nvsm``'s only evidence; the full system and ``no_inpaint`` add it to the
            rendered views when ``AgentConfig.match_observations``).
        observation_match_is_nvsm: count those crop matches as the entry's NVSM runs (``no_nvsm``).
        inpaint: complete the holes of rendered views before matching (off for ``no_vcicn``).
        inpainter: the plug-in spec of the completion step (:func:`splatsearch.plugins.make_inpainter`):
            ``AgentConfig.inpainter`` resolved ("auto": "vcicn" when the package ships VCICN
            weights, else "opencv"), "opencv" for ``opencv_inpaint``; None without completion.
        colour_cue: compare each detection's colours with the goal object's
            (``AgentConfig.colour_cue``).
    """

    frontier_terms: bool
    nvsm_during_search: bool
    identify_after_exploring: bool
    match_observations: bool
    observation_match_is_nvsm: bool
    inpaint: bool
    colour_cue: bool
    inpainter: str | None = None


@dataclass
class AgentConfig:
    """Agent settings (metres, steps, pixels, counts; defaults in the field list).

    variant: one of :data:`VARIANTS`, resolved by :func:`resolve_variant`.

    Mapping: every ``map_every``-th frame is mapped at ``map_scale`` of the camera resolution
    with ``map_iters`` Adam steps and densify stride ``map_stride`` px. The online map serves
    lifting and the viewer; the NVSM renders object-local maps at full resolution
    (``local_map``: :class:`~splatsearch.search.local_map.LocalMapConfig`). ``nvsm_fill``:
    "global" composites the online map's renders of the NVSM cameras under the local map's, so
    that what the local map never covered, up to the view's edge, shows the coarse online map
    instead of a hole ("none" leaves them holes). ``nvsm_fill_crop``: that online-map
    render is cropped to the local map's region (False: the whole house).

    Identification: ``tau_m`` (inliers) is eq 18's match threshold on camera-image counts,
    ``nvsm_tau_m`` the same for rendered views (matched with a lower SIFT contrast threshold); an
    NVSM count is stored as ``e_max * tau_m / nvsm_tau_m`` so that one e_max and one tau_m serve
    eq 18 and eq 20. ``f_O``: NVSM period in new viewpoints; ``tau_d`` (m): object merge distance;
    ``n_views``, ``view_radius`` (m), ``view_elevations_deg``, ``inpaint_tau`` (opacity below
    which a rendered pixel is a hole): the NVSM hemisphere. ``clear_views``: keep only hemisphere
    cameras over known free space with a line of sight to the object on the occupancy grid.
    ``nvsm_max_runs``: NVSM runs per object at most. ``match_observations``: the full system and
    ``no_vcicn`` also match the real crop around each new detection. ``identify_every_frame``:
    detect and lift in every frame, not only in mapped ones (the masked depth places detections
    between mapped frames).

    Colour cue (:mod:`splatsearch.search.appearance`): with ``colour_cue`` each detection's
    masked colours are compared with the goal object's (the goal object's mask comes from the
    detector run on the goal image). An object is the goal when its weighted mean colour
    similarity over at least ``colour_min_views`` viewpoints reaches ``tau_a``, or when it passes
    tau_m (eq 18) and its colour similarity is not below ``colour_veto``; a detection's weight
    grows with its mask up to ``colour_full_px`` pixels. Objects the cue already decides get no
    feature matching (it could not change the decision).

    Look again (issue 23): ``look_again`` is the number of new viewpoints from which an
    ambiguous goal-class object is looked at again (0: none); ambiguous means at least one NVSM
    run, not the goal, and a best count e_max of at least ``look_again_low`` but below tau_m. The
    robot walks (FMM) to a free cell about ``look_again_distance`` m from the object, reachable
    within ``look_again_max_path`` m of path, at the azimuth that its stored observations miss most
    and the last NVSM run's renders left emptiest (look_again.choose_viewpoint), turns to face it,
    adds that frame to the object's observations and runs its NVSM again. A trip that takes more
    than ``look_again_steps`` steps is abandoned (it still counts as one of the object's views);
    the moves are episode steps, and an object taken for the goal ends the look-again.

    Confirm (issue 23, the default since stop 45, when its dev rule passed, docs/results.md).
    ``confirm_below`` is the upper end (inliers, camera-image scale) of the marginal matches that
    get a confirm trip, off at or below tau_m (an absolute count, so raising tau_m to 18 or more
    turns it off). An object taken for the goal by feature matches alone whose e_max is in
    [tau_m, confirm_below) is looked at once from another side (the viewpoint choice and trip of
    the look-again step) before the robot walks to it. The new frame's count decides, not the
    running maximum, which keeps every run's best and could never take a false match back. The
    largest count recorded for the object in the capture step (the crop match of that frame and
    the NVSM run that includes it) must reach tau_m on its own, or the match is refuted, no longer
    taken for the goal unless its e_max later reaches confirm_below, while the end-of-exploration
    fallback still ranks it by e_max. A confirm trip that finds no viewpoint, no path or runs past
    the look-again step limit leaves the match as it was. ``confirm_by`` is "new_frame" (the trip
    above) or "rivals" (no trip to the marginal match, but while it is the best goal candidate the
    ambiguous objects get their look-again trips first, since one may be the goal and overtake it,
    and with none left the match stands). ``look_again_after_refute`` lets look-again trips begin
    only once a confirm trip has refuted a match in the episode (a look-alike is about, so the
    ambiguous objects are worth a trip). ``refute_radius`` (m, 0 = off, default 1.0 = ``tau_d``):
    a refusal also covers every same-class entry whose centroid lies within this distance of the
    refuted one's, a duplicate DB entry of the same physical object, for as long as neither has
    reached confirm_below (centroids drift as views accumulate, so two entries made more than
    ``tau_d`` apart can end up on one object). Issue 23: built at stop 47, the default since
    stop 48, where its dev rule passed on 8 episodes of houses 508-509 (none of which had a
    duplicate to refuse).

    Planning: ``alpha``, ``beta``, ``delta``: eq 19 weights. ``stop_margin`` (m): stop this close
    to a goal object's extent. ``goal_patience``: reachable steps without getting 0.1 m closer
    to a goal object before it is given up. ``verify_steps``: steps spent next to an object whose
    colours match from too few viewpoints, turning toward it, before giving it up.
    ``grid_shape``: cells of the 2-D maps (5 cm) around the start. ``seed``: mapper seeds.

    Plug-ins, as :mod:`splatsearch.plugins` spec strings (picklable, so evaluation workers build
    their own): ``detector`` is the goal-class detector ("sim" is the simulator's ground-truth
    masks, an oracle; "yolo:PATH[,sam=PATH]" a local YOLO model); ``matcher`` scores camera crops
    and, built for renders, the NVSM views ("sift", or "loftr:PATH"); ``inpainter`` completes the
    NVSM views ("auto": the shipped VCICN, or OpenCV when no weights are shipped; "vcicn",
    "vcicn:PATH", "opencv"; ``opencv_inpaint`` always uses "opencv"). Objects passed to
    :class:`SplatSearchAgent` take precedence.
    """

    variant: str = "splatsearch"
    map_every: int = 3
    map_scale: float = 0.25
    map_iters: int = 5
    map_stride: int = 2
    tau_m: float = DEFAULT_TAU_M
    nvsm_tau_m: float = RENDER_TAU_M
    f_O: int = 3
    tau_d: float = 1.0
    n_views: int = 12
    view_radius: float = 1.5
    view_elevations_deg: tuple = (20.0, 45.0)
    inpaint_tau: float = 0.5
    clear_views: bool = True
    nvsm_fill: str = "none"
    nvsm_fill_crop: bool = True
    nvsm_max_runs: int = 3
    match_observations: bool = True
    local_map: LocalMapConfig = field(default_factory=LocalMapConfig)
    alpha: float = 1.0
    beta: float = 1.0
    delta: float = 0.5
    stop_margin: float = 0.6
    goal_patience: int = 60
    identify_every_frame: bool = True
    verify_steps: int = 6
    look_again: int = 1
    look_again_low: float = 9.0
    look_again_distance: float = 1.6
    look_again_max_path: float = 8.0
    look_again_steps: int = 40
    look_again_after_refute: bool = True
    confirm_below: float = 18.0
    confirm_by: str = "new_frame"
    refute_radius: float = 1.0
    colour_cue: bool = True
    tau_a: float = 0.45
    colour_min_views: int = 2
    colour_veto: float = 0.2
    colour_full_px: int = 3000
    grid_shape: tuple = (600, 600)
    seed: int = 0
    detector: str = "sim"
    matcher: str = "sift"
    inpainter: str = "auto"

    def __post_init__(self):
        self.variant = canonical_variant(self.variant)
        if not (self.tau_m > 0 and self.nvsm_tau_m > 0):
            raise ValueError(f"need tau_m > 0 and nvsm_tau_m > 0, got {self.tau_m}, {self.nvsm_tau_m}")
        if self.nvsm_fill not in ("none", "global"):
            raise ValueError(f"nvsm_fill must be 'none' or 'global', got {self.nvsm_fill!r}")
        if self.map_every < 1 or not 0 < self.map_scale <= 1 or self.n_views < 1:
            raise ValueError("need map_every >= 1, 0 < map_scale <= 1 and n_views >= 1")
        if self.look_again < 0 or self.look_again_steps < 1 or not (
                self.look_again_distance > 0 and self.look_again_max_path > 0 and self.look_again_low >= 0):
            raise ValueError("need look_again >= 0, look_again_steps >= 1, look_again_distance > 0, "
                             "look_again_max_path > 0 and look_again_low >= 0")
        if self.confirm_by not in ("new_frame", "rivals"):
            raise ValueError(f"confirm_by must be 'new_frame' or 'rivals', got {self.confirm_by!r}")
        if not (np.isfinite(self.refute_radius) and self.refute_radius >= 0):
            raise ValueError(f"refute_radius must be a distance >= 0 m (0: off), got {self.refute_radius}")
        if not self.confirm_below >= 0:
            raise ValueError(f"confirm_below must be >= 0 (at or below tau_m: off), got {self.confirm_below}")
        if not (0 <= self.colour_veto <= self.tau_a <= 1) or self.colour_min_views < 1 \
                or self.colour_full_px < 1:
            raise ValueError("need 0 <= colour_veto <= tau_a <= 1, colour_min_views >= 1 and "
                             "colour_full_px >= 1")


def resolve_variant(cfg: AgentConfig) -> Strategy:
    """The :class:`Strategy` of ``cfg.variant`` (with ``cfg``'s own switches folded in)."""
    v = canonical_variant(cfg.variant)
    inpaint = v != "no_vcicn"
    if not inpaint:
        inpainter = None
    elif v == "opencv_inpaint":
        inpainter = "opencv"
    else:
        from splatsearch.plugins import resolve_inpainter_spec

        inpainter = resolve_inpainter_spec(cfg.inpainter)
    return Strategy(
        frontier_terms=v not in ("nearest_frontier", "gaussnav"),
        nvsm_during_search=v not in ("no_nvsm", "gaussnav"),
        identify_after_exploring=v == "gaussnav",
        match_observations=v == "no_nvsm" or (cfg.match_observations
                                              and v in ("splatsearch", "no_vcicn", "opencv_inpaint")),
        observation_match_is_nvsm=v == "no_nvsm",
        inpaint=inpaint,
        colour_cue=bool(cfg.colour_cue),
        inpainter=inpainter,
    )
