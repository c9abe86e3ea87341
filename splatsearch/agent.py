"""The SplatSearch agent (thesis Chapter 4): sense -> map -> identify -> plan -> act.

One :meth:`SplatSearchAgent.act` call per simulator step:

1. the exploration planner fuses depth into the occupancy grid and the goal-image cosine into the
   value map (eq 11-12);
2. every ``map_every``-th frame the Gaussian mapper adds the frame (eq 3-10) at the mapping
   resolution; the detector's goal-class masks are lifted onto the Gaussians that render them
   (the rasterizer's per-pixel top-contributor ids; between mapped frames, and wherever the ids
   disagree with it, the masked depth), then merged into the object DB (eq 13), and each
   detection's colours are compared with the goal object's (:mod:`splatsearch.search.appearance`);
3. every object seen from ``f_O`` new viewpoints gets the NVSM: ``n_views`` hemisphere views
   rendered from the map, holes (alpha < tau) inpainted, and feature matches against the goal
   image counted; e_max >= tau_m marks it as the goal (eq 18) unless its colours rule it out;
   an object whose colours match over enough viewpoints is the goal without it, and the NVSM is
   skipped for objects the colours already decide;
4. with a goal object the agent follows the FMM path to it and stops within ``stop_margin`` of
   its extent; with an object that looks like the goal from too few viewpoints it walks up to it
   to confirm it; otherwise it takes the eq 19/20 frontier;
5. once no frontier is left and no object passed tau_m, it goes to the goal-class object with
   the most evidence (appearance, then e_max) and stops there rather than where it stands; that
   choice is made again every step with some hysteresis, since the way there shows the other
   objects again (the thesis does not say what happens then).

Variants (the thesis' Table IV ablations): ``splatsearch`` (full), ``no_nvsm`` (match the raw
observation of each detection instead of rendered views), ``no_inpaint``, ``nearest_frontier``
(eq 19 with alpha only) and ``gaussnav`` (explore everything first, then identify and go); and
``no_appearance`` (the full system without the colour cue of
:mod:`splatsearch.search.appearance`, which every other variant uses).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from splatsearch.mapper import Mapper, MapperConfig
from splatsearch.nav.encoders import ColorTextureEncoder, ImageEncoder, cosine
from splatsearch.nav.exploration import (
    ExplorationConfig,
    ExplorationPlanner,
    ObjectScore,
)
from splatsearch.nav.grid import GridSpec, wrap_angle
from splatsearch.nav.occupancy import FREE, OCCUPIED
from splatsearch.search.appearance import (
    AppearanceModel,
    ColorHistogramAppearance,
    goal_object_mask,
)
from splatsearch.search.detection import Detector, SimDetector, check_detections
from splatsearch.search.inpainting import Inpainter, OpenCVInpainter
from splatsearch.search.local_map import (
    LocalMapConfig,
    ObservationStore,
    build_local_map,
    region_box,
)
from splatsearch.search.matching import (
    DEFAULT_TAU_M,
    RENDER_TAU_M,
    Matcher,
    SIFTMatcher,
)
from splatsearch.search.novel_views import clear_viewpoints, hemisphere_viewpoints
from splatsearch.search.object_search import NVSMConfig, verify_object
from splatsearch.search.objects import (
    ObjectDB,
    ObjectEntry,
    lift_mask_depth,
    lift_mask_ids,
    map_top_ids,
)

#: context kept around a detection's box when its real observation is matched, as a fraction of
#: the box size. On 4 explored houses (val-hard goals, every same-class instance seen from >= 150
#: px), the goal instance ranked first by its best crop count in 3/4 episodes with 1.0 against 1/4
#: with 0.5: the goal image shows the object in its surroundings.
MATCH_CROP_MARGIN = 1.0

#: metres between the Gaussian-id lift of a detection and its depth lift beyond which the depth lift
#: is used (the coarse online map has not resolved the object yet).
LIFT_TOLERANCE = 0.5

#: hysteresis of the end-of-exploration fallback (:meth:`SplatSearchAgent._choose_fallback`): another
#: entry replaces the current one only when its appearance is higher by more than this, or when it
#: is about as similar and has at least ``FALLBACK_MATCH_MARGIN`` more matches (camera-image scale)
FALLBACK_APPEARANCE_MARGIN = 0.05
FALLBACK_MATCH_MARGIN = 2.0

#: the smallest goal image side in pixels: SIFT finds almost no features below it
MIN_GOAL_SIDE = 32

#: the thesis' Table IV rows (the evaluation's default) and ``no_appearance``: the full system
#: identifying by feature matches alone, as the thesis does
VARIANTS = ("splatsearch", "no_nvsm", "no_inpaint", "nearest_frontier", "gaussnav", "no_appearance")
EVAL_VARIANTS = VARIANTS[:5]


@dataclass
class AgentConfig:
    """Agent settings.

    variant: one of :data:`VARIANTS`.
    map_every: map (and detect) every k-th frame; map_scale: mapping resolution relative to the
    camera; map_iters / map_stride: optimisation steps per mapped frame and densify stride. The
    defaults (every 3rd frame at 80x60, 5 steps: ~0.12 s per mapped frame on 2 cores against
    0.52 s at 160x120 with 10 steps) keep the online map cheap: it serves lifting and the viewer,
    while the NVSM renders full-resolution local maps of each object (``nvsm_map="local"``).
    tau_m, f_O, tau_d: match threshold (inliers), NVSM trigger period (viewpoints), merge
    distance (m). nvsm_tau_m: the threshold for the counts on rendered novel views, which are
    matched with a lower SIFT contrast threshold than camera images (default 15, as tau_m; 20
    was measured and lost SPL, see :data:`~splatsearch.search.matching.RENDER_TAU_M`); an NVSM
    count is recorded as ``e_max * tau_m / nvsm_tau_m`` so that one e_max and one tau_m serve
    eq 18 and eq 20. n_views, view_radius (m), view_elevations_deg, inpaint_tau: the NVSM.
    clear_views: keep only hemisphere cameras over known free space with a clear line of sight to
    the object on the occupancy grid (cameras behind a wall see only its back).
    nvsm_map: "local" renders the NVSM views from a full-resolution map of the object's region
    built from its stored observations (:mod:`splatsearch.search.local_map`); "global" renders
    the online house map. local_map: the settings of those maps. nvsm_max_runs: NVSM runs per
    object at most (each local map costs a few seconds on a CPU; later runs add little).
    match_observations: the full system (and no_inpaint) also matches the real observation around
    each new detection, as no_nvsm does; the rendered views then add viewpoints the robot never
    had. gaussnav identifies after exploring and matches rendered views only.
    inspect (off by default: no gain measured yet): walk up to unverified goal-class objects
    (within ``inspect_range`` m geodesic) until ``inspect_distance`` m from their extent, face them, and run their NVSM with that close view
    (at most ``inspect_steps`` steps each). Objects first seen across a room fill a few dozen
    pixels, too few for feature matching however the views are rendered; not used by gaussnav,
    which identifies only after exploring.
    alpha, beta, delta: eq 19 weights. stop_margin: the agent stops this close (m) to a matched
    object's extent (Habitat success: within 1 m of the object's navigable viewpoints).
    goal_patience: steps without getting 0.1 m closer to a matched object before the agent gives
    it up and turns to the next candidate.
    identify_every_frame: detect and lift goal-class objects in every frame, not only in mapped
    ones (between them the masked depth places the detections): an object glimpsed while turning
    gets three times the views.
    verify_steps: an object that looks like the goal from too few viewpoints is approached; once
    there, the agent turns toward it for at most this many steps to confirm it, else gives it up.
    appearance: also compare the colours of each detection with the goal object's
    (:mod:`splatsearch.search.appearance`; needs the goal object's mask, from the detector run on
    the goal image). An object is the goal when its weighted mean similarity over at least
    ``appearance_min_views`` viewpoints reaches ``tau_a``, or when it passes tau_m (eq 18) and
    its appearance is not below ``appearance_veto``; a detection's weight grows with its mask up
    to ``appearance_full_px`` pixels. Objects the appearance rules out get no NVSM or feature
    matching (neither could change the decision), and neither do objects it already confirms.
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
    nvsm_map: str = "local"
    nvsm_max_runs: int = 3
    match_observations: bool = True
    local_map: LocalMapConfig = field(default_factory=LocalMapConfig)
    inspect: bool = False
    inspect_distance: float = 1.0
    inspect_range: float = 6.0
    inspect_steps: int = 40
    alpha: float = 1.0
    beta: float = 1.0
    delta: float = 0.5
    stop_margin: float = 0.6
    goal_patience: int = 60
    identify_every_frame: bool = True
    verify_steps: int = 6
    appearance: bool = True
    tau_a: float = 0.45
    appearance_min_views: int = 2
    appearance_veto: float = 0.2
    appearance_full_px: int = 3000
    grid_shape: tuple = (600, 600)
    seed: int = 0

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {self.variant!r}")
        if self.nvsm_map not in ("local", "global"):
            raise ValueError(f"nvsm_map must be 'local' or 'global', got {self.nvsm_map!r}")
        if not (self.tau_m > 0 and self.nvsm_tau_m > 0):
            raise ValueError(f"need tau_m > 0 and nvsm_tau_m > 0, got {self.tau_m}, {self.nvsm_tau_m}")
        if self.map_every < 1 or not 0 < self.map_scale <= 1 or self.n_views < 1:
            raise ValueError("need map_every >= 1, 0 < map_scale <= 1 and n_views >= 1")
        if not (0 <= self.appearance_veto <= self.tau_a <= 1) or self.appearance_min_views < 1 \
                or self.appearance_full_px < 1:
            raise ValueError("need 0 <= appearance_veto <= tau_a <= 1, appearance_min_views >= 1 and "
                             "appearance_full_px >= 1")


@dataclass
class StepInfo:
    """What the agent did this step (for progress displays and the viewer)."""

    action: str
    status: str
    n_frontiers: int = 0
    n_objects: int = 0
    best_score: float = 0.0
    nvsm_runs: int = 0
    timings: dict = field(default_factory=dict)


@dataclass
class NovelViews:
    """The latest NVSM run: object id, cameras (V, 4, 4), renders, inpainted views, counts."""

    entry_id: int
    viewmats: np.ndarray
    rendered: np.ndarray
    inpainted: np.ndarray
    counts: np.ndarray
    best: int


class SplatSearchAgent:
    """Instance-image-goal search in an unknown house.

    Args:
        K, width, height: the robot camera.
        goal_rgb: (H, W, 3) goal image, float in [0, 1] or uint8; its size need not be the robot
            camera's, but at least :data:`MIN_GOAL_SIDE` px a side. goal_class: its object class
            (a goal category).
        start_pose: (x, y, yaw) where the episode starts (centres the grid maps).
        config: :class:`AgentConfig`; detector / matcher / inpainter / encoder / appearance_model:
            plug-ins (offline defaults: simulator masks, SIFT + RANSAC, OpenCV Telea,
            colour+texture, masked hue-saturation histogram). ``matcher`` scores the camera
            images around detections; ``nvsm_matcher`` scores the rendered novel views (default:
            ``matcher`` when one is given, else SIFT with
            :data:`~splatsearch.search.matching.RENDER_CONTRAST_THRESHOLD`, because renders of a
            Gaussian map are softer than camera images).
        goal_mask: (H, W) bool, the goal object's pixels in the goal image. Without it the
            detector is run on the goal image (``goal_frame`` is passed to it: the simulator
            detector needs the goal image's frame); without either the appearance cue is off.

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
                 appearance_model: AppearanceModel | None = None, nvsm_matcher: Matcher | None = None):
        self.cfg = cfg = config or AgentConfig()
        self.K = np.asarray(K, np.float64)
        self.W, self.H = int(width), int(height)
        self.goal = _check_goal_image(goal_rgb)
        self.goal_class = goal_class
        self.detector = detector or SimDetector(goal_classes=(goal_class,))
        self.appearance_model = appearance_model or ColorHistogramAppearance()
        use_appearance = cfg.appearance and cfg.variant != "no_appearance"
        self._goal_sig = self._goal_signature(goal_mask, goal_frame) if use_appearance else None
        self.matcher = matcher or SIFTMatcher()
        self.nvsm_matcher = nvsm_matcher or matcher or SIFTMatcher.for_renders()
        self.inpainter = inpainter or OpenCVInpainter()
        only_alpha = cfg.variant in ("nearest_frontier", "gaussnav")
        ecfg = ExplorationConfig(alpha=cfg.alpha, beta=0.0 if only_alpha else cfg.beta,
                                 delta=0.0 if only_alpha else cfg.delta, tau_m=cfg.tau_m)
        spec = GridSpec.centered(np.asarray(start_pose)[:2], cfg.grid_shape)
        self.encoder = encoder or ColorTextureEncoder()
        self.explorer = ExplorationPlanner(spec, ecfg, encoder=self.encoder)
        self._goal_embedding = np.asarray(self.encoder.embed(self.goal), np.float32)
        # per object: best embedding cosine between the goal image and a detection's crop; it
        # only breaks ties between candidates when exploration ends with no match above tau_m
        self.appearance: dict[int, float] = {}
        if ecfg.delta > 0:
            self.explorer.set_goal_image(self.goal)
        # mapping camera: the robot camera scaled down
        s = cfg.map_scale
        self.mW, self.mH = max(8, round(self.W * s)), max(8, round(self.H * s))
        self.mK = self.K.copy()
        self.mK[:2] *= np.array([[self.mW / self.W], [self.mH / self.H]])
        self.mapper = Mapper(self.mK.astype(np.float32), self.mW, self.mH,
                             MapperConfig(iters=cfg.map_iters, stride=cfg.map_stride, seed=cfg.seed))
        self.db = ObjectDB(tau_d=cfg.tau_d, f_O=cfg.f_O)
        self._nvsm = NVSMConfig(radius=cfg.view_radius, n_views=cfg.n_views,
                                elevations_deg=tuple(cfg.view_elevations_deg), alpha_tau=cfg.inpaint_tau,
                                tau_m=cfg.nvsm_tau_m, inpaint=cfg.variant != "no_inpaint")
        # a local map holds only the object's region: what lies outside it is background to fill
        # flat, not holes to inpaint
        self._nvsm_local = replace(self._nvsm, crop=True, crop_margin=0.0, floor_z=None)
        self._match_observations = cfg.match_observations and cfg.variant in ("splatsearch", "no_inpaint", "no_appearance")
        self.observations = ObservationStore(cfg.local_map.max_frames, cfg.local_map.min_separation)
        self.frame_index = 0
        self.nvsm_runs = 0
        self.last_views: NovelViews | None = None
        self.last_decision = None
        self.target_entry: int | None = None
        self.path_xy: np.ndarray = np.zeros((0, 2))
        self._explored = False
        self._given_up: set[int] = set()
        self._fallback: int | None = None
        self._verify: tuple[int, int] | None = None
        self._goal_progress: list | None = None
        self._inspected: set[int] = set()
        self._inspecting: int | None = None
        self._inspect_start = 0
        self._last_obs = None
        self._last_frame = None

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
        return self.appearance_model.signature(self.goal, goal_mask)

    # -- one step -------------------------------------------------------------------------------
    def act(self, rgb: np.ndarray, depth: np.ndarray, viewmat: np.ndarray, pose, frame=None) -> StepInfo:
        """Sense one observation and return the next action in a :class:`StepInfo`.

        rgb (H, W, 3), depth (H, W) metres, viewmat (4, 4) world-to-camera of the (odometry) pose,
        pose (x, y, yaw); ``frame`` is passed to the detector (the simulator's masks).
        """
        t = {}
        t0 = time.perf_counter()
        pose = np.asarray(pose, np.float64)
        self._last_obs, self._last_frame = (rgb, depth, viewmat), frame
        self.explorer.observe(depth, viewmat, self.K, pose, rgb)
        t["nav"] = time.perf_counter() - t0
        mapped = self.frame_index % self.cfg.map_every == 0
        if mapped:
            t1 = time.perf_counter()
            small_rgb = cv2.resize(np.asarray(rgb, np.float32), (self.mW, self.mH), interpolation=cv2.INTER_AREA)
            small_d = cv2.resize(np.asarray(depth, np.float32), (self.mW, self.mH), interpolation=cv2.INTER_NEAREST)
            self.mapper.update(small_rgb, small_d, viewmat)
            t["map"] = time.perf_counter() - t1
        if mapped or self.cfg.identify_every_frame:
            t1 = time.perf_counter()
            self._identify(rgb, depth, viewmat, pose, frame, use_map=mapped)
            t["identify"] = time.perf_counter() - t1
        self.frame_index += 1
        t1 = time.perf_counter()
        action, status = self._decide(pose)
        # the explorer only sees its own actions; a blocked step toward a goal must mark the
        # obstacle too, or the goal plan repeats the same bump forever
        self.explorer.note_action(action)
        t["plan"] = time.perf_counter() - t1
        fr = self.last_decision.frontiers if self.last_decision is not None else []
        best = max([e.e_max for e in self.db] + [0.0])
        return StepInfo(action, status, len(fr), len(self.db), best, self.nvsm_runs, t)

    # -- SOIM + NVSM + FEM ----------------------------------------------------------------------
    def _detect(self, rgb: np.ndarray, frame) -> list:
        """The detector's output for ``rgb``, checked (a list of Detection with masks of the
        image's size; a plug-in's mistake is reported here rather than deep in the lifting)."""
        return check_detections(self.detector.detect(rgb, frame), np.shape(rgb)[:2], type(self.detector).__name__)

    def _identify(self, rgb, depth, viewmat, pose, frame, use_map: bool = True) -> None:
        dets = [d for d in self._detect(rgb, frame) if d.label == self.goal_class]
        if not dets:
            return
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
                means = np.asarray(self.mapper.map.means)
                lifted = lift_mask_ids(mask, ids, means, active=np.asarray(self.mapper.map.active), erode_px=1)
            by_depth = lift_mask_depth(d.mask, depth, viewmat, self.K, erode_px=1)
            if lifted is None or (by_depth is not None and
                                  np.linalg.norm(lifted.centroid - by_depth.centroid) > LIFT_TOLERANCE):
                # too few Gaussians under a small mask at the mapping resolution, or Gaussians of
                # what lies behind the object (the coarse map has not resolved it yet): the
                # full-resolution masked depth places it instead
                lifted = by_depth
            if lifted is None:
                continue
            res = self.db.add_lifted(d.label, lifted, viewmat)
            if res.new_viewpoint:
                sim = cosine(self.encoder.embed(_crop_around(rgb, d.mask)), self._goal_embedding)
                self.appearance[res.entry_id] = max(sim, self.appearance.get(res.entry_id, -1.0))
                if self._goal_sig is not None:
                    a = self.appearance_model.similarity(self._goal_sig, self.appearance_model.signature(rgb, d.mask))
                    w = min(d.n_pixels, self.cfg.appearance_full_px) / self.cfg.appearance_full_px
                    self.db.record_appearance(res.entry_id, min(max(a, 0.0), 1.0), w)
            if res.new_viewpoint and self.cfg.nvsm_map == "local":
                self.observations.add(res.entry_id, rgb, depth, viewmat)
            if res.new_viewpoint and (self.cfg.variant == "no_nvsm" or self._match_observations) \
                    and self._matching_can_decide(self.db[res.entry_id]):
                # the detection's neighbourhood in the real frame: the no_nvsm ablation's only
                # evidence, and the full system's too when match_observations is on (the NVSM
                # adds rendered views to the real ones)
                n = self._match_detection(rgb, d.mask)
                self.db.record_match(res.entry_id, float(n), 0, self.cfg.tau_m,
                                     nvsm_run=self.cfg.variant == "no_nvsm")
        if self.cfg.variant in ("no_nvsm", "gaussnav"):
            self.db.pop_pending()  # gaussnav identifies after exploring; no_nvsm matched above
            return
        for eid in self.db.pop_pending():
            if self.db[eid].n_nvsm < self.cfg.nvsm_max_runs and self._matching_can_decide(self.db[eid]):
                self._run_nvsm(eid)

    def _appearance_says_goal(self, e) -> bool:
        return (self._goal_sig is not None and e.app_views >= self.cfg.appearance_min_views
                and e.appearance >= self.cfg.tau_a)

    def _appearance_rules_out(self, e) -> bool:
        return self._goal_sig is not None and e.app_views > 0 and e.appearance < self.cfg.appearance_veto

    def _matching_can_decide(self, e) -> bool:
        """Whether feature matching (raw or NVSM) could still change what the agent makes of entry
        ``e``: not when its appearance already rules it out or already confirms it."""
        return not (self._appearance_rules_out(e) or self._appearance_says_goal(e))

    def _identifies_now(self) -> bool:
        """gaussnav identifies only once it has explored everything; the others all along."""
        return self.cfg.variant != "gaussnav" or self._explored

    def is_goal(self, e: ObjectEntry) -> bool:
        """Whether entry ``e`` is taken for the goal: its appearance confirms it, or it passed
        tau_m (eq 18) and its appearance does not rule it out."""
        return self._appearance_says_goal(e) or (e.matched and not self._appearance_rules_out(e))

    def goal_candidates(self) -> list[ObjectEntry]:
        """Entries taken for the goal and not given up, most likely first (appearance, then
        e_max). gaussnav identifies only once it has explored everything."""
        if not self._identifies_now():
            return []
        out = [e for e in self.db if e.id not in self._given_up and self.is_goal(e)]
        return sorted(out, key=lambda e: (-e.appearance, -e.e_max))

    def _choose_fallback(self) -> ObjectEntry | None:
        """Once everything is explored and nothing passed tau_m: the goal-class entry with the
        best evidence (appearance, then e_max, then the best single-view colour similarity), or
        None when there is none. It is chosen again every step, because walking to it shows the
        other entries again and their e_max can overtake it; the current choice is kept unless
        another entry beats it by ``FALLBACK_APPEARANCE_MARGIN`` in appearance or, at about the
        same appearance, by ``FALLBACK_MATCH_MARGIN`` matches, so near-ties (common, and the
        third key changes every frame) do not make the robot turn back and forth."""
        cands = [e for e in self.db if e.id not in self._given_up]
        if not cands:
            self._fallback = None
            return None
        best = max(cands, key=lambda e: (e.appearance, e.e_max, self.appearance.get(e.id, -1.0)))
        cur = next((e for e in cands if e.id == self._fallback), None)
        if cur is not None and best.id != cur.id:
            d_app = best.appearance - cur.appearance
            switch = d_app > FALLBACK_APPEARANCE_MARGIN or (
                d_app >= -FALLBACK_APPEARANCE_MARGIN and best.e_max >= cur.e_max + FALLBACK_MATCH_MARGIN)
            if not switch:
                best = cur
        self._fallback = best.id
        return best

    def _promising(self) -> list[ObjectEntry]:
        """Entries whose appearance reaches tau_a from too few viewpoints to confirm them, most
        similar first: the agent walks up to them to see them again."""
        if self._goal_sig is None or not self._identifies_now():
            return []
        out = [e for e in self.db if e.id not in self._given_up and not self.is_goal(e)
               and e.appearance >= self.cfg.tau_a]
        return sorted(out, key=lambda e: -e.appearance)

    def _match_detection(self, rgb: np.ndarray, mask: np.ndarray) -> int:
        """Feature matches between the goal image and the real observation around a detection:
        rgb (H, W, 3), mask (H, W) bool; the crop keeps ``MATCH_CROP_MARGIN`` of context."""
        return int(self.matcher.count(self.goal, _crop_around(rgb, mask, margin=MATCH_CROP_MARGIN)))

    def _run_nvsm(self, eid: int) -> None:
        cfg = self.cfg
        e = self.db[eid]
        obs = self.observations[eid]
        if cfg.nvsm_map == "local" and obs and e.bbox_min is not None:
            lo, hi = region_box(e.bbox_min, e.bbox_max, cfg.local_map.margin)
            gmap = build_local_map(obs, self.K, self.W, self.H, lo, hi, cfg.local_map, seed=cfg.seed)
            score = verify_object(self.goal, gmap, e.centroid, self.K, self.W, self.H, matcher=self.nvsm_matcher,
                                  inpainter=self.inpainter, config=self._nvsm_local, bbox=(lo, hi),
                                  viewmats=self._nvsm_viewpoints(e))
        else:
            # the whole map is rendered, not a crop around the object: the goal image shows the
            # object in its surroundings, and those surroundings carry many of the matches
            score = verify_object(self.goal, self.mapper.map, e.centroid, self.K, self.W, self.H,
                                  matcher=self.nvsm_matcher, inpainter=self.inpainter, config=self._nvsm,
                                  viewmats=self._nvsm_viewpoints(e))
        # on the camera-image scale, so eq 18's tau_m and eq 20's scores treat both kinds alike
        scaled = float(score.e_max) * cfg.tau_m / cfg.nvsm_tau_m
        self.db.record_match(eid, scaled, score.i_star, cfg.tau_m, score.viewmats[score.i_star])
        self.nvsm_runs += 1
        self.last_views = NovelViews(eid, score.viewmats, score.rendered, score.images, score.counts, score.i_star)

    def _nvsm_viewpoints(self, e) -> np.ndarray | None:
        """The NVSM cameras of entry ``e``: ``n_views`` spread over the hemisphere cameras (three
        times as many candidates) that stand over known free space with a clear line of sight to
        the object on the occupancy grid; None (the plain hemisphere) when too few are clear, or
        when ``clear_views`` is off."""
        cfg = self.cfg
        if not cfg.clear_views:
            return None
        cands = hemisphere_viewpoints(e.centroid, cfg.view_radius, 3 * cfg.n_views, cfg.view_elevations_deg)
        occ = self.explorer.occupancy
        keep = clear_viewpoints(cands, occ.state == OCCUPIED, occ.spec, e.centroid[:2], skip_radius=e.extent_radius,
                                free=occ.state == FREE)
        idx = np.flatnonzero(keep)
        if len(idx) < max(2, cfg.n_views // 4):
            return None
        if len(idx) > cfg.n_views:
            idx = idx[np.linspace(0, len(idx) - 1, cfg.n_views).round().astype(int)]
        return cands[idx]

    # -- planning -------------------------------------------------------------------------------
    def _decide(self, pose, *, after_exploring: bool = False) -> tuple[str, str]:
        matched = self.goal_candidates()
        if self._explored and not matched:
            if self.cfg.variant == "gaussnav":
                for e in self.db:
                    if e.n_nvsm == 0 and self._matching_can_decide(e):
                        self._run_nvsm(e.id)
                matched = self.goal_candidates()
            if not matched:
                # everything is explored and nothing passed tau_m: the goal-class object with the
                # most evidence is still a better bet than stopping where the robot is
                best = self._choose_fallback()
                if best is not None:
                    matched = [best]
        verifying = False
        if not matched:
            matched = self._promising()
            verifying = bool(matched)
        if matched:
            e = matched[0]
            self.target_entry = e.id
            planner = self.explorer.planner()
            radius = e.extent_radius + self.cfg.stop_margin
            plan = planner.plan(pose, e.centroid[:2], radius)
            try:
                self.path_xy = planner.path(pose[:2], e.centroid[:2], radius)
            except Exception:  # noqa: BLE001 - the path is for display only
                self.path_xy = np.zeros((0, 2))
            if plan.status in ("reached", "closest"):
                if verifying:
                    return self._look_at(pose, e)
                return "stop", "goal_reached"
            if np.isfinite(plan.distance) and self._goal_stalled(e.id, plan.distance):
                self._given_up.add(e.id)  # no progress for a long while: try the next candidate
                return "turn_left", "stuck_goal"
            if plan.status == "unreachable":
                if after_exploring or self._explored:
                    self._given_up.add(e.id)  # no way to it on the map: try the next candidate
                    return "turn_left", "unreachable_goal"
                return self._explore(pose, "exploring_to_goal")  # the way to it is not mapped yet
            return plan.action, "to_candidate" if verifying else "to_goal"
        if after_exploring:
            return "stop", "explored"
        inspect = self._inspect(pose)
        if inspect is not None:
            return inspect
        return self._explore(pose, "exploring")

    def _look_at(self, pose, e) -> tuple[str, str]:
        """Next to an unconfirmed candidate: turn toward it so the next frames see it, and give it
        up after ``verify_steps`` steps there without confirming it."""
        if self._verify is None or self._verify[0] != e.id:
            self._verify = (e.id, self.frame_index)
        err = _bearing_error(pose, e.centroid)
        if self.frame_index - self._verify[1] >= self.cfg.verify_steps:
            self._given_up.add(e.id)
            return "turn_left", "not_the_goal"
        if abs(err) > np.radians(20):
            return ("turn_left" if err > 0 else "turn_right"), "verifying"
        # facing it: wait for the next frames by looking left and right of it in turn
        return ("turn_left" if (self.frame_index - self._verify[1]) % 2 else "turn_right"), "verifying"

    def _goal_stalled(self, entry_id: int, distance: float) -> bool:
        """True when the geodesic distance to goal entry ``entry_id`` has not dropped by 0.1 m in
        ``goal_patience`` reachable steps (the robot keeps bumping into something the map lacks).
        Steps where the goal is unreachable on the map are not counted: the agent is exploring
        toward it then."""
        if self._goal_progress is None or self._goal_progress[0] != entry_id:
            self._goal_progress = [entry_id, np.inf, 0]
        if distance < self._goal_progress[1] - 0.1:
            self._goal_progress[1:] = [distance, 0]
            return False
        self._goal_progress[2] += 1
        return self._goal_progress[2] > self.cfg.goal_patience

    def _inspect(self, pose) -> tuple[str, str] | None:
        """Walk to the nearest unverified goal-class object, face it, verify it with that view."""
        cfg = self.cfg
        if not cfg.inspect or cfg.variant == "gaussnav":
            return None
        planner = self.explorer.planner()
        if self._inspecting is None:
            todo = [e for e in self.db if not (e.id in self._inspected or e.id in self._given_up or self.is_goal(e))]
            if not todo:
                return None
            D = planner.distance_from(pose[:2])  # one FMM for all candidates
            cands = []
            for e in todo:
                rs, cs, inside = planner.spec.cells_within(e.centroid[:2], e.extent_radius + cfg.inspect_distance)
                d = D[rs, cs][inside]
                d = float(d.min()) if d.size else np.inf
                if d <= cfg.inspect_range:
                    cands.append((d, e.id))
            if not cands:
                return None
            self._inspecting, self._inspect_start = min(cands)[1], self.frame_index
        e = self.db[self._inspecting]
        plan = planner.plan(pose, e.centroid[:2], e.extent_radius + cfg.inspect_distance)
        timed_out = self.frame_index - self._inspect_start > cfg.inspect_steps
        if plan.status in ("unreachable", "blocked") or timed_out:
            self._inspected.add(e.id)
            self._inspecting = None
            return None
        self.target_entry = e.id
        if plan.status not in ("reached", "closest"):
            try:
                self.path_xy = planner.path(pose[:2], e.centroid[:2], e.extent_radius + cfg.inspect_distance)
            except Exception:  # noqa: BLE001 - the path is for display only
                self.path_xy = np.zeros((0, 2))
            return plan.action, "inspecting"
        # there: turn until the object is ahead, then verify it with this close view
        err = _bearing_error(pose, e.centroid)
        if abs(err) > np.radians(20) and self.frame_index - self._inspect_start <= cfg.inspect_steps:
            return ("turn_left" if err > 0 else "turn_right"), "inspecting"
        self._inspected.add(e.id)
        self._inspecting = None
        if self._last_obs is not None and cfg.variant != "no_nvsm":
            rgb, depth, viewmat = self._last_obs
            if cfg.nvsm_map == "local":
                self.observations.add(e.id, rgb, depth, viewmat)
            self._run_nvsm(e.id)
        elif self._last_obs is not None:
            dets = [d for d in self._detect(self._last_obs[0], self._last_frame) if d.label == self.goal_class]
            for d in dets:
                n = self._match_detection(self._last_obs[0], d.mask)
                if n > max(e.e_max, 0):
                    self.db.record_match(e.id, float(n), 0, cfg.tau_m)
        if self.is_goal(e):
            return self._decide(pose)
        return None

    def _explore(self, pose, label: str) -> tuple[str, str]:
        cents, scores = self.db.scores()
        if self._goal_sig is not None:
            # eq 20 in match units: an object that looks like the goal draws the robot to the
            # frontiers around it as a tau_m match would
            app = np.array([max(e.appearance, 0.0) for e in self.db])
            scores = np.maximum(scores, self.cfg.tau_m * app / max(self.cfg.tau_a, 1e-6)) if len(app) else scores
        objs = [ObjectScore(c[:2], s) for c, s in zip(cents, scores)]
        d = self.explorer.act(pose, objs)
        self.last_decision = d
        if d.target is not None:
            self.path_xy = np.asarray([pose[:2], d.target.waypoint_xy])
        if d.status == "explored":
            self._explored = True
            return self._decide(pose, after_exploring=True)
        return d.action, label if d.status == "exploring" else d.status


def _bearing_error(pose, xy) -> float:
    """Turn (rad, in [-pi, pi), positive = left) from robot ``pose`` (x, y, yaw) to face world
    point ``xy`` (its first two coordinates, metres)."""
    dx, dy = xy[0] - pose[0], xy[1] - pose[1]
    return float(wrap_angle(np.arctan2(dy, dx) - pose[2]))


def _crop_around(rgb: np.ndarray, mask: np.ndarray, margin: float = 0.5, min_size: int = 32) -> np.ndarray:
    """The image region around a mask's bounding box, grown by ``margin`` of its size and to at
    least ``min_size`` pixels a side (a sliver of a mask still gives the matcher a patch)."""
    rows, cols = np.nonzero(mask)
    if len(rows) == 0:
        return rgb
    H, W = mask.shape
    r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    dr = max(int((r1 - r0) * margin), (min_size - (r1 - r0) + 1) // 2)
    dc = max(int((c1 - c0) * margin), (min_size - (c1 - c0) + 1) // 2)
    return rgb[max(0, r0 - dr):min(H, r1 + dr), max(0, c0 - dc):min(W, c1 + dc)]


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
