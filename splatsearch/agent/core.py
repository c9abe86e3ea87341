"""The SplatSearch agent (thesis Chapter 4): sense -> map -> identify -> plan -> act.

One :meth:`SplatSearchAgent.act` call per simulator step drives three rooms in one direction:

1. :class:`~splatsearch.agent.perception.Perception`: the occupancy grid and value map are fused
   by the explorer (eq 11-12); every ``map_every``-th frame goes into the Gaussian map (eq 3-10);
   the goal-class detections are lifted onto the map and merged into the object DB (eq 13), with
   their colours compared to the goal object's;
2. :class:`~splatsearch.agent.verification.Verifier`: each new detection's camera crop is matched
   against the goal image, and every object seen from ``f_O`` new viewpoints gets the NVSM
   (eq 14-18) unless its colours already decide it;
3. :class:`~splatsearch.agent.decision.SearchPolicy`: the target (a goal object, an object to
   look at again, the eq 19/20 frontier, or the end-of-exploration fallback) and the action
   toward it, asked of the :class:`~splatsearch.nav.exploration.ExplorationPlanner`, which sees
   the action taken in the next frame's ``observe``.

Variants (the thesis' Table IV ablations, :data:`~splatsearch.agent.config.VARIANTS`) are
resolved once into a :class:`~splatsearch.agent.config.Strategy`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from splatsearch.nav.encoders import ColorTextureEncoder, ImageEncoder
from splatsearch.nav.exploration import ExplorationConfig, ExplorationPlanner
from splatsearch.nav.grid import GridSpec
from splatsearch.search.appearance import AppearanceModel, ColorHistogramAppearance
from splatsearch.search.detection import Detector
from splatsearch.search.inpainting import Inpainter
from splatsearch.search.matching import Matcher

from .config import AgentConfig, resolve_variant
from .decision import SearchPolicy
from .perception import Perception
from .verification import Verifier

#: the smallest goal image side in pixels: SIFT finds almost no features below it
MIN_GOAL_SIDE = 32


@dataclass
class StepInfo:
    """What the agent did this step (for progress displays and the viewer): the action, a status
    word, frontiers and objects known, the best e_max, NVSM runs so far, and seconds per stage."""

    action: str
    status: str
    n_frontiers: int = 0
    n_objects: int = 0
    best_score: float = 0.0
    nvsm_runs: int = 0
    timings: dict = field(default_factory=dict)


class SplatSearchAgent:
    """Instance-image-goal search in an unknown house.

    State lives in the three rooms: :attr:`perception` (map, object DB, observations),
    :attr:`verifier` (match counts, NVSM runs), :attr:`policy` (explored, given-up entries,
    targets); :attr:`explorer` holds the 2-D maps. The properties below read them for the viewer
    and the episode runner.

    Args:
        K, width, height: the robot camera.
        goal_rgb: (H, W, 3) goal image, float in [0, 1] or uint8; its size need not be the robot
            camera's, but at least :data:`MIN_GOAL_SIDE` px a side. goal_class: its object class
            (a goal category).
        start_pose: (x, y, yaw) where the episode starts (centres the grid maps).
        config: :class:`AgentConfig`; detector / matcher / inpainter / encoder / colour_model:
            plug-ins (defaults: ``config.detector`` and ``config.matcher`` specs, i.e. the
            simulator's masks and SIFT + RANSAC; OpenCV Telea, colour+texture, masked
            hue-saturation histogram for the colour cue). ``matcher``
            scores the camera crops around detections; ``nvsm_matcher`` scores the rendered novel
            views (default:
            ``matcher`` when one is given, else SIFT with
            :data:`~splatsearch.search.matching.RENDER_CONTRAST_THRESHOLD`, because renders of a
            Gaussian map are softer than camera images).
        goal_mask: (H, W) bool, the goal object's pixels in the goal image. Without it the
            detector is run on the goal image (``goal_frame`` is passed to it: the simulator
            detector needs the goal image's frame); without either the colour cue is off.

    Raises:
        ValueError: for a goal image that is not RGB, is smaller than ``MIN_GOAL_SIDE`` px a side,
            holds NaN / Inf or values outside [0, 1]; for a goal mask of another size; and, from
            :meth:`act`, when a detector's mask does not have the image's size.
        TypeError: for a goal image of a non-numeric dtype, and when the detector returns
            anything but a list of :class:`~splatsearch.search.Detection`.
    """

    def __init__(self, K, width: int, height: int, goal_rgb: np.ndarray, goal_class: str, start_pose, *,
                 config: AgentConfig | None = None, detector: Detector | None = None,
                 matcher: Matcher | None = None, inpainter: Inpainter | None = None,
                 encoder: ImageEncoder | None = None, goal_mask: np.ndarray | None = None, goal_frame=None,
                 colour_model: AppearanceModel | None = None, nvsm_matcher: Matcher | None = None):
        self.cfg = cfg = config or AgentConfig()
        self.strategy = strategy = resolve_variant(cfg)
        self.K = np.asarray(K, np.float64)
        self.W, self.H = int(width), int(height)
        self.goal = _check_goal_image(goal_rgb)
        self.goal_class = goal_class
        from splatsearch.plugins import make_detector, make_inpainter, make_matcher

        encoder = encoder or ColorTextureEncoder()
        if nvsm_matcher is None:  # an explicit matcher also scores the renders, as before
            nvsm_matcher = matcher or make_matcher(cfg.matcher, renders=True)
        matcher = matcher or make_matcher(cfg.matcher)
        detector = detector or make_detector(cfg.detector, goal_classes=(goal_class,))
        self.perception = Perception(self.K, self.W, self.H, self.goal, goal_class, cfg,
                                     detector=detector, encoder=encoder,
                                     colour_model=colour_model or ColorHistogramAppearance(),
                                     colour_cue=strategy.colour_cue, goal_mask=goal_mask, goal_frame=goal_frame)
        self.verifier = Verifier(self.goal, self.K, self.W, self.H, cfg, strategy, matcher=matcher,
                                 nvsm_matcher=nvsm_matcher,
                                 inpainter=inpainter or make_inpainter(strategy.inpainter or "opencv"),
                                 colour_cue=self.perception.goal_signature is not None)
        terms = strategy.frontier_terms
        ecfg = ExplorationConfig(alpha=cfg.alpha, beta=cfg.beta if terms else 0.0, delta=cfg.delta if terms else 0.0,
                                 tau_m=cfg.tau_m)
        self.explorer = ExplorationPlanner(GridSpec.centered(np.asarray(start_pose)[:2], cfg.grid_shape), ecfg,
                                           encoder=encoder)
        if ecfg.delta > 0:
            self.explorer.set_goal_image(self.goal)
        self.policy = SearchPolicy(cfg, strategy, self.perception.db, self.verifier, self.explorer,
                                   self.perception.crop_cosine, observations=self.perception.observations)
        self.frame_index = 0
        self._last_action: str | None = None
        self._frame_now: tuple | None = None  # (rgb, depth, viewmat) of the step being decided

    # -- what the viewer and the episode runner read ------------------------------------------
    @property
    def db(self):
        """The object DB (:class:`~splatsearch.search.ObjectDB`)."""
        return self.perception.db

    @property
    def mapper(self):
        """The online Gaussian mapper (:class:`~splatsearch.mapper.Mapper`)."""
        return self.perception.mapper

    @property
    def nvsm_runs(self) -> int:
        return self.verifier.nvsm_runs

    @property
    def last_views(self):
        """The latest NVSM run's views (:class:`~splatsearch.agent.verification.NovelViews`) or None."""
        return self.verifier.last_views

    @property
    def path_xy(self) -> np.ndarray:
        """(P, 2) world metres: the path the robot follows now (for display)."""
        return self.policy.path_xy

    @property
    def last_decision(self):
        """The explorer's latest frontier :class:`~splatsearch.nav.exploration.Decision` or None."""
        return self.policy.last_decision

    @property
    def target_entry(self) -> int | None:
        return self.policy.target_entry

    def is_goal(self, e) -> bool:
        """Whether object entry ``e`` is taken for the goal (see :meth:`Verifier.is_goal`)."""
        return self.verifier.is_goal(e)

    def goal_candidates(self) -> list:
        """Entries taken for the goal and not given up, most likely first."""
        return self.policy.goal_candidates()

    # -- one step -------------------------------------------------------------------------------
    def act(self, rgb: np.ndarray, depth: np.ndarray, viewmat: np.ndarray, pose, frame=None) -> StepInfo:
        """Sense one observation and return the next action in a :class:`StepInfo`.

        rgb (H, W, 3), depth (H, W) metres, viewmat (4, 4) world-to-camera of the (odometry) pose,
        pose (x, y, yaw); ``frame`` is passed to the detector (the simulator's masks).
        """
        t = {}
        t0 = time.perf_counter()
        pose = np.asarray(pose, np.float64)
        self.verifier.new_step()
        self.explorer.observe(depth, viewmat, self.K, pose, rgb, action=self._last_action)
        t["nav"] = time.perf_counter() - t0
        mapped = self.frame_index % self.cfg.map_every == 0
        if mapped:
            t1 = time.perf_counter()
            self.perception.map_frame(rgb, depth, viewmat)
            t["map"] = time.perf_counter() - t1
        if mapped or self.cfg.identify_every_frame:
            t1 = time.perf_counter()
            self._identify(rgb, depth, viewmat, frame, use_map=mapped)
            t["identify"] = time.perf_counter() - t1
        self.frame_index += 1
        t1 = time.perf_counter()
        self._frame_now = (rgb, depth, viewmat)
        action, status = self.policy.decide(pose, self.frame_index, verify_all=self._verify_unverified,
                                            capture=self._look_again_capture)
        self._frame_now = None
        self._last_action = action
        t["plan"] = time.perf_counter() - t1
        d = self.policy.last_decision
        best = max([e.e_max for e in self.db] + [0.0])
        return StepInfo(action, status, len(d.frontiers) if d is not None else 0, len(self.db), best,
                        self.verifier.nvsm_runs, t)

    def _identify(self, rgb, depth, viewmat, frame, use_map: bool) -> None:
        db, verifier, strategy = self.db, self.verifier, self.strategy
        for view in self.perception.observe(rgb, depth, viewmat, frame, use_map=use_map):
            if strategy.match_observations and verifier.can_decide(db[view.entry_id]):
                verifier.match_observation(db, view.entry_id, rgb, view.detection.mask)
        due = db.pop_pending()
        if not strategy.nvsm_during_search:
            return
        for eid in due:
            if db[eid].n_nvsm < self.cfg.nvsm_max_runs and verifier.can_decide(db[eid]):
                verifier.verify(db, eid, self.perception.observations, self.explorer.occupancy, self._fill_map())

    def _verify_unverified(self) -> None:
        """After exploring (gaussnav): the NVSM of every object that has had none."""
        for e in self.db:
            if e.n_nvsm == 0 and self.verifier.can_decide(e):
                self.verifier.verify(self.db, e.id, self.perception.observations, self.explorer.occupancy,
                                     self._fill_map())

    def _look_again_capture(self, entry_id: int) -> None:
        """The look-again step faces entry ``entry_id`` from a new viewpoint: keep this frame among its
        observations (so its local map includes it) and run its NVSM again."""
        rgb, depth, viewmat = self._frame_now
        self.perception.observations.add(entry_id, rgb, depth, viewmat)
        self.verifier.verify(self.db, entry_id, self.perception.observations, self.explorer.occupancy,
                             self._fill_map())

    def _fill_map(self):
        """The map composited under the NVSM's local-map renders (``AgentConfig.nvsm_fill``)."""
        return self.perception.mapper.map if self.cfg.nvsm_fill == "global" else None


def _check_goal_image(goal_rgb) -> np.ndarray:
    """The goal image as float32 (H, W, 3) in [0, 1]. uint8 images are scaled by 1/255; anything
    else that is not an RGB image of at least ``MIN_GOAL_SIDE`` pixels a side with finite values
    in [0, 1] is rejected, because it would only fail (or silently match nothing) mid-episode."""
    g = np.asarray(goal_rgb)
    if g.ndim != 3 or g.shape[2] != 3:
        raise ValueError(f"goal_rgb must have shape (H, W, 3), got {g.shape}")
    if min(g.shape[:2]) < MIN_GOAL_SIDE:
        raise ValueError(f"goal_rgb is {g.shape[1]}x{g.shape[0]} px; it needs at least {MIN_GOAL_SIDE} px a side "
                         "for feature matching")
    if g.dtype == np.uint8:
        return g.astype(np.float32) / 255.0
    if not np.issubdtype(g.dtype, np.floating):
        raise TypeError(f"goal_rgb must be float in [0, 1] or uint8, got dtype {g.dtype}")
    g = g.astype(np.float32)
    if not np.all(np.isfinite(g)):
        raise ValueError("goal_rgb contains NaN or Inf")
    lo, hi = float(g.min()), float(g.max())
    if lo < -1e-3 or hi > 1.0 + 1e-3:
        hint = " (a 0-255 image? divide it by 255)" if hi > 1.5 else ""
        raise ValueError(f"goal_rgb values must be in [0, 1], got [{lo:.3g}, {hi:.3g}]{hint}")
    return np.clip(g, 0.0, 1.0)
