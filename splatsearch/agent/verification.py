"""Verification: is this object the goal? (thesis Sections 4.2.3-4.2.5, eq 18).

Two kinds of evidence reach an object entry: feature-match counts against the goal image, from
the real camera crop around a detection (:meth:`Verifier.match_observation`) or from the NVSM
(:meth:`Verifier.verify`: a full-resolution local map of the object's region built from its
stored observations, hemisphere views rendered from it, holes inpainted, the best view's count),
and the colour cue that perception records. :meth:`Verifier.is_goal` combines them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from splatsearch.nav.occupancy import FREE, OCCUPIED, OccupancyGrid
from splatsearch.search.inpainting import Inpainter, holes_from_alpha
from splatsearch.search.local_map import ObservationStore, build_local_map, region_box
from splatsearch.search.matching import Matcher
from splatsearch.search.novel_views import clear_viewpoints, hemisphere_viewpoints
from splatsearch.search.object_search import NVSMConfig, NVSMResult, verify_object
from splatsearch.search.objects import ObjectDB, ObjectEntry

from .config import AgentConfig, Strategy
from .perception import crop_around

#: context kept around a detection's box when its real observation is matched, as a fraction of
#: the box size: the goal image shows the object in its surroundings
MATCH_CROP_MARGIN = 1.0


@dataclass
class NovelViews:
    """The latest NVSM run (for the viewer): entry id, cameras (V, 4, 4) world-to-camera, renders
    (V, H, W, 3), the inpainted views (V, H, W, 3), counts (V,) and the best view's index."""

    entry_id: int
    viewmats: np.ndarray
    rendered: np.ndarray
    inpainted: np.ndarray
    counts: np.ndarray
    best: int


class Verifier:
    """Feature matching, the NVSM and the goal decision for one episode's goal image.

    Args:
        goal: (H, W, 3) float32 goal image in [0, 1].
        K (3, 3), width, height: the robot camera, also used for the NVSM views.
        config, strategy: :class:`AgentConfig` and its resolved :class:`Strategy`.
        matcher: scores camera crops; nvsm_matcher: scores rendered views; inpainter: completes
            them.
        colour_cue: whether colour similarities are recorded (perception found the goal object
            in the goal image); without it the decision rests on feature matches alone.

    State: :attr:`nvsm_runs` (NVSM runs so far), :attr:`last_views` (the latest run's views) and
    :attr:`view_holes` (entry id -> (cameras (V, 4, 4), fraction of each render left empty) of its
    latest run, for the look-again step) and :attr:`step_counts` (entry id -> the largest count,
    camera-image scale, recorded for it since :meth:`new_step`: what the current frame alone says,
    which the confirm trip decides on) and, for diagnosis only, :attr:`count_log` (entry id -> a
    list of [step, "crop" or "nvsm", count] of every non-zero count recorded for it, camera-image
    scale; the step as :meth:`new_step` counts them, the policy's step index).
    """

    def __init__(self, goal: np.ndarray, K: np.ndarray, width: int, height: int, config: AgentConfig,
                 strategy: Strategy, *, matcher: Matcher, nvsm_matcher: Matcher, inpainter: Inpainter,
                 colour_cue: bool):
        self.goal = goal
        self.K = np.asarray(K, np.float64)
        self.W, self.H = int(width), int(height)
        self.cfg, self.strategy = config, strategy
        self.matcher, self.nvsm_matcher, self.inpainter = matcher, nvsm_matcher, inpainter
        self.colour_cue = bool(colour_cue)
        # a local map holds only the object's region: what lies outside it is background to fill
        # flat, not holes to inpaint
        self.nvsm_config = NVSMConfig(radius=config.view_radius, n_views=config.n_views,
                                      elevations_deg=tuple(config.view_elevations_deg), alpha_tau=config.inpaint_tau,
                                      tau_m=config.nvsm_tau_m, inpaint=strategy.inpaint, crop=True, crop_margin=0.0,
                                      floor_z=None, fill_crop=config.nvsm_fill_crop)
        self.nvsm_runs = 0
        self.last_views: NovelViews | None = None
        self.view_holes: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.step_counts: dict[int, float] = {}
        self.count_log: dict[int, list] = {}
        self._step = 0

    def new_step(self) -> None:
        """Forget :attr:`step_counts` (the agent calls this before it senses a new frame)."""
        self.step_counts = {}
        self._step += 1

    def _note(self, entry_id: int, count: float, kind: str = "crop") -> None:
        self.step_counts[entry_id] = max(self.step_counts.get(entry_id, 0.0), float(count))
        if count > 0:  # zeros are most crops of far objects: kept out so the log stays small
            self.count_log.setdefault(entry_id, []).append([self._step, kind, round(float(count), 2)])

    # -- the decision -----------------------------------------------------------------------
    def colour_confirms(self, e: ObjectEntry) -> bool:
        """The colours of ``e`` match the goal's over at least ``colour_min_views`` viewpoints."""
        return (self.colour_cue and e.colour_views >= self.cfg.colour_min_views
                and e.colour_similarity >= self.cfg.tau_a)

    def colour_rules_out(self, e: ObjectEntry) -> bool:
        """The colours of ``e`` are below ``colour_veto``."""
        return self.colour_cue and e.colour_views > 0 and e.colour_similarity < self.cfg.colour_veto

    def can_decide(self, e: ObjectEntry) -> bool:
        """Whether feature matching could still change what is made of ``e``: not when its colours
        already rule it out or already confirm it."""
        return not (self.colour_rules_out(e) or self.colour_confirms(e))

    def is_goal(self, e: ObjectEntry) -> bool:
        """Whether ``e`` is taken for the goal: its colours confirm it, or it passed tau_m (eq 18)
        and its colours do not rule it out."""
        return self.colour_confirms(e) or (e.matched and not self.colour_rules_out(e))

    def looks_promising(self, e: ObjectEntry) -> bool:
        """Colours that reach ``tau_a`` from too few viewpoints to confirm it: worth a closer look."""
        return self.colour_cue and not self.is_goal(e) and e.colour_similarity >= self.cfg.tau_a

    def is_ambiguous(self, e: ObjectEntry) -> bool:
        """The NVSM left ``e`` undecided: at least one run, not taken for the goal, feature matches
        could still decide it, and its best count (camera-image scale) is at least
        ``look_again_low`` but below tau_m. The look-again step looks at such objects again."""
        return (e.n_nvsm > 0 and not self.is_goal(e) and self.can_decide(e)
                and self.cfg.look_again_low <= e.e_max < self.cfg.tau_m)

    # -- evidence ---------------------------------------------------------------------------
    def match_observation(self, db: ObjectDB, entry_id: int, rgb: np.ndarray, mask: np.ndarray) -> int:
        """Match the goal image against the camera crop around a detection (rgb (H, W, 3), mask
        (H, W) bool; ``MATCH_CROP_MARGIN`` of context) and record the count; returns it."""
        n = int(self.matcher.count(self.goal, crop_around(rgb, mask, margin=MATCH_CROP_MARGIN)))
        db.record_match(entry_id, float(n), 0, self.cfg.tau_m, nvsm_run=self.strategy.observation_match_is_nvsm)
        self._note(entry_id, n, "crop")
        return n

    def verify(self, db: ObjectDB, entry_id: int, observations: ObservationStore,
               occupancy: OccupancyGrid | None = None, fill_map=None) -> NVSMResult | None:
        """Run the NVSM of entry ``entry_id`` and record its best count (on the camera-image
        scale). Needs the entry's extent and at least one stored observation; returns None (and
        records nothing) without them. ``occupancy``: picks cameras with a clear view
        (``clear_views``)."""
        cfg = self.cfg
        e = db[entry_id]
        obs = observations[entry_id]
        if not obs or e.bbox_min is None:
            return None
        lo, hi = region_box(e.bbox_min, e.bbox_max, cfg.local_map.margin)
        gmap = build_local_map(obs, self.K, self.W, self.H, lo, hi, cfg.local_map, seed=cfg.seed)
        score = verify_object(self.goal, gmap, e.centroid, self.K, self.W, self.H, matcher=self.nvsm_matcher,
                              inpainter=self.inpainter, config=self.nvsm_config, bbox=(lo, hi),
                              viewmats=self.nvsm_viewpoints(e, occupancy), fill_map=fill_map)
        # on the camera-image scale, so eq 18's tau_m and eq 20's scores treat both kinds alike
        scaled = float(score.e_max) * cfg.tau_m / cfg.nvsm_tau_m
        db.record_match(entry_id, scaled, score.i_star, cfg.tau_m, score.viewmats[score.i_star])
        self._note(entry_id, scaled, "nvsm")
        self.nvsm_runs += 1
        self.last_views = NovelViews(entry_id, score.viewmats, score.rendered, score.images, score.counts, score.i_star)
        empty = (holes_from_alpha(score.alpha, self.nvsm_config.alpha_tau) if score.alpha is not None
                 else np.asarray(score.holes, bool))
        self.view_holes[entry_id] = (np.asarray(score.viewmats, np.float64), empty.reshape(len(empty), -1).mean(1))
        return score

    def nvsm_viewpoints(self, e: ObjectEntry, occupancy: OccupancyGrid | None) -> np.ndarray | None:
        """The NVSM cameras (V, 4, 4) of entry ``e``: ``n_views`` spread over the hemisphere
        cameras (three times as many candidates) that stand over known free space with a clear
        line of sight to the object on the occupancy grid; None (the plain hemisphere) when too
        few are clear, without a grid, or when ``clear_views`` is off."""
        cfg = self.cfg
        if not cfg.clear_views or occupancy is None:
            return None
        cands = hemisphere_viewpoints(e.centroid, cfg.view_radius, 3 * cfg.n_views, cfg.view_elevations_deg)
        keep = clear_viewpoints(cands, occupancy.state == OCCUPIED, occupancy.spec, e.centroid[:2],
                                skip_radius=e.extent_radius, free=occupancy.state == FREE)
        idx = np.flatnonzero(keep)
        if len(idx) < max(2, cfg.n_views // 4):
            return None
        if len(idx) > cfg.n_views:
            idx = idx[np.linspace(0, len(idx) - 1, cfg.n_views).round().astype(int)]
        return cands[idx]
