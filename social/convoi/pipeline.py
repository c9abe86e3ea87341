"""CoNVOI (Sathyamoorthy et al. 2024): context -> behaviour prompt -> marked image -> VLM -> reference
path, with extrapolation and re-querying (IV-A..IV-E). The DWA side (eq 5, 6) lives in
:mod:`.costs` / :mod:`.dwa`; :func:`splatsearch.social.convoi.runner.run_episode` ties them together.

Every control step :meth:`CoNVOI.update`:

1. perceives: the people in line of sight, O_t with and without them (robot frame), the goal
   direction (a carrot on the static route), detected groups;
2. classifies the context c_t (:mod:`.context`);
3. without a reference path: queries the VLM (eq 4) with I_t^Mark (:mod:`.mmvm`) and the behaviour
   prompt of c_t; the chosen markers become T_ref, stored in the world frame and re-expressed
   in the robot frame every step;
4. with one, once the robot is within ``d_thresh`` of its last point (IV-E):
   * same context as when it was queried: fit a line to T_ref (robot frame), extend it by
     ``d_extend`` past the last point; if that point is obstacle-free (eq 2) and its image patch is
     paved (the classifier's ``is_paved``), append it; otherwise query;
   * context changed: query.
   A failed query (``ok=False``) clears the path, so the DWA runs without the reference
   critic, and the next query waits ``retry_s``. A simulated ``latency_s`` delays each answer.

With a ground-truth route (:meth:`CoNVOI.set_ground_truth`, e.g. the expert's trajectory), each
query is also scored like CoNVOI's Table I: reference-path error and cosine similarity against
the markers a human would pick (per row, the marker nearest to the route), and whether the
chosen path is unacceptable.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from . import metrics
from .context import (
    ContextClassifier,
    RuleContextClassifier,
    SceneObservation,
    behaviour_prompt,
)
from .geometry import DistanceField, robot_to_world, world_to_robot
from .mmvm import (
    CameraModel,
    MarkerGrid,
    Markers,
    crop_patch,
    line_of_sight,
    mark,
    render_view,
)
from .perception import detect_groups, group_pairs, local_maps, visible_people
from .vlm import VLM, MarkerScene, VLMResult

DEFAULT_GRID = MarkerGrid(rows=3, cols=9, d_row=1.2, d_col=0.45, first_row=1.2)
DEFAULT_CAMERA = CameraModel.from_fov(320, 240, 90.0, height_m=0.6, pitch=-0.35)


@dataclass(frozen=True)
class CoNVOIConfig:
    """grid: the l x m candidates; camera: the robot camera; d_thresh: re-query / extrapolation
    distance to the last reference point (m; the paper: v_max * t_query); d_extend: extrapolation
    length (m); n_pat: paved-check patch size (px); local_n, local_cell: O_t size (cells, m);
    sensor_range: m; retry_s: wait after a failed query (s); min_query_interval: s between two
    queries (a real VLM answers in seconds); stall_s, stall_distance: a robot that moved less than
    stall_distance m in stall_s s while following a reference path drops it and runs plain DWA
    for stall_s s (the explicit way out of a reference path that leads into a dead end);
    latency_s: simulated VLM latency (s);
    max_ref: reference points kept; goal_lookahead: how far along the route the goal direction
    is taken (m); max_extrapolation_angle: an extrapolation direction farther than this (rad)
    from the goal direction is refused (our guard; the paper does not say)."""

    grid: MarkerGrid = DEFAULT_GRID
    camera: CameraModel = DEFAULT_CAMERA
    d_thresh: float = 1.5
    d_extend: float = 1.0
    n_pat: int = 48
    local_n: int = 200
    local_cell: float = 0.05
    sensor_range: float = 8.0
    retry_s: float = 1.0
    min_query_interval: float = 1.0
    stall_s: float = 3.0
    stall_distance: float = 0.15
    latency_s: float = 0.0
    max_ref: int = 16
    goal_lookahead: float = 3.0
    max_extrapolation_angle: float = 0.7854
    robot_radius: float = 0.25
    person_radius: float = 0.25

    def __post_init__(self):
        if self.d_thresh <= 0 or self.d_extend <= 0 or self.n_pat < 4 or self.retry_s < 0 or self.latency_s < 0:
            raise ValueError("need d_thresh, d_extend > 0, n_pat >= 4, retry_s and latency_s >= 0")


@dataclass
class QueryRecord:
    """One VLM query: time (s), robot pose, context, prompt, the result, the chosen reference
    path and the ground-truth one (robot frame, (k, 2)), and its Table I scores."""

    t: float
    pose: np.ndarray
    context: str
    prompt: str
    result: VLMResult
    n_markers: int
    ref_robot: np.ndarray
    gt_robot: np.ndarray | None = None
    error: float | None = None
    cosine: float | None = None
    unacceptable: bool | None = None


@dataclass
class Observation:
    people_world: np.ndarray
    people_robot: np.ndarray
    vel_robot: np.ndarray
    groups: np.ndarray
    scene: SceneObservation
    goal_robot: np.ndarray


class CoNVOI:
    """The CoNVOI reference-path provider (see the module doc).

    Args:
        vlm: the large VLM (:class:`~splatsearch.social.convoi.vlm.VLM`).
        classifier: the context classifier (default :class:`RuleContextClassifier`).
        cfg: :class:`CoNVOIConfig`.
    """

    def __init__(self, vlm: VLM, classifier: ContextClassifier | None = None, cfg: CoNVOIConfig = CoNVOIConfig()):
        self.vlm = vlm
        self.classifier = classifier if classifier is not None else RuleContextClassifier()
        self.cfg = cfg
        self.gt_world: np.ndarray | None = None
        self._reset_state()

    def _reset_state(self):
        self.ref: np.ndarray | None = None
        self.ref_context: str | None = None
        self.pending: tuple[float, np.ndarray, str] | None = None
        self.next_query_t = 0.0
        self.queries: list[QueryRecord] = []
        self.extrapolations = 0
        self.extrapolation_refusals = 0
        self.contexts: collections.Counter = collections.Counter()
        self.context_now: str | None = None
        self.last_marked: np.ndarray | None = None
        self.last_markers: Markers | None = None
        self.field: DistanceField | None = None
        self.last_query_t = -np.inf
        self.history: collections.deque = collections.deque()
        self.stalls = 0

    def reset(self, scn=None, world=None) -> None:
        """Forget the reference path and the statistics (a new episode)."""
        self._reset_state()

    def set_ground_truth(self, path_world) -> None:
        """The route (N, 2) world points that the ground-truth reference paths follow (e.g. the
        expert's trajectory); None disables the Table I scores."""
        self.gt_world = None if path_world is None else np.asarray(path_world, np.float64)[:, :2]

    # -- perception ---------------------------------------------------------------------------
    def observe(self, pose, peds, world) -> Observation:
        """People in sight, O_t with and without them, and the goal direction, at ``pose``."""
        cfg = self.cfg
        pose = np.asarray(pose, np.float64)
        vis = np.asarray(visible_people(jnp.asarray(pose, jnp.float32), peds.pos, peds.active, world.capsules,
                                        world.capsules_valid, cfg.sensor_range))
        pw = np.asarray(peds.pos, np.float64)[vis]
        vw = np.asarray(peds.vel, np.float64)[vis]
        pr = world_to_robot(pw, pose) if len(pw) else np.zeros((0, 2))
        c, s = np.cos(pose[2]), np.sin(pose[2])
        vr = vw @ np.array([[c, -s], [s, c]]) if len(vw) else np.zeros((0, 2))
        groups = detect_groups(pw, vw) if len(pw) else np.zeros(0, np.int64)
        static, full = local_maps(world.field, pose, pw, n=cfg.local_n, cell=cfg.local_cell,
                                  inflate=cfg.robot_radius, person_radius=cfg.person_radius)
        from .runner import carrot_jit  # the same route-following rule as the DWA's

        g = np.asarray(carrot_jit(world.path, world.path_valid, jnp.asarray(pose[:2], jnp.float32), world.goal,
                                  cfg.goal_lookahead))
        goal_r = world_to_robot(g, pose)
        scene = SceneObservation(full, static, pr, vr, groups, goal_r)
        return Observation(pw, pr, vr, groups, scene, goal_r)

    # -- the IV-E loop --------------------------------------------------------------------
    def update(self, t: float, pose, peds, world) -> np.ndarray | None:
        """One control step at time ``t`` (s), robot ``pose`` (3,) world. Returns the current
        reference path (k, 2) in world coordinates, or None (plain DWA)."""
        pose = np.asarray(pose, np.float64)
        cfg = self.cfg
        if self.pending is not None and t + 1e-9 >= self.pending[0]:
            _, self.ref, self.ref_context = self.pending
            self.pending = None
        self.history.append((t, pose[:2].copy(), self.ref is not None))
        while self.history and self.history[0][0] < t - cfg.stall_s - 1e-9:
            self.history.popleft()
        if (self.ref is not None and len(self.history) > 1 and t - self.history[0][0] >= cfg.stall_s - 1e-9
                and all(h[2] for h in self.history)
                and np.linalg.norm(pose[:2] - self.history[0][1]) < cfg.stall_distance):
            self.stalls += 1
            self.ref, self.ref_context = None, None
            self.next_query_t = t + cfg.stall_s
            self.history.clear()
        obs = self.observe(pose, peds, world)
        image = None
        if getattr(self.classifier, "needs_image", True):
            image = render_view(obs.scene.static_map, self.cfg.camera, obs.people_robot, self.cfg.person_radius)
        ctx = self.classifier.classify(image, obs.scene)
        self.context_now = ctx.label
        self.contexts[ctx.label] += 1
        if self.pending is not None or t + 1e-9 < self.last_query_t + cfg.min_query_interval:
            return self.ref
        if self.ref is None or not len(self.ref):
            if t + 1e-9 >= self.next_query_t:
                self._query(t, pose, obs, ctx.label, image)
            return self.ref
        rob = world_to_robot(self.ref, pose)
        # the last point is near, or the robot has passed every point (eq 5 has nothing ahead)
        used_up = np.linalg.norm(rob[-1]) < cfg.d_thresh or not np.any(rob[:, 0] > 0)
        if used_up and t + 1e-9 >= self.next_query_t:
            if ctx.label == self.ref_context and self._extrapolate(pose, obs, image):
                self.extrapolations += 1
            else:
                self._query(t, pose, obs, ctx.label, image)
        return self.ref

    def _query(self, t, pose, obs: Observation, context: str, image=None):
        cfg = self.cfg
        self.last_query_t = t
        if image is None:
            image = render_view(obs.scene.static_map, cfg.camera, obs.people_robot, cfg.person_radius)
        marked, markers = mark(image, obs.scene.local_map, cfg.camera, cfg.grid)
        self.last_marked, self.last_markers = marked, markers
        table = getattr(self.classifier, "contexts", None)
        prompt = behaviour_prompt(context, table)
        lm = obs.scene.local_map
        scene = MarkerScene(markers, obs.people_robot, obs.vel_robot, obs.groups, obs.goal_robot, lm.clearance_at)
        if len(markers.labels) == 0:
            res = VLMResult(False, error="no marker passed the line-of-sight test", source="mmvm")
        else:
            res = self.vlm.select_labels(marked, prompt, markers.labels.tolist(), scene)
        rec = QueryRecord(t, pose.copy(), context, prompt, res, len(markers.labels), np.zeros((0, 2)))
        if res.ok:
            try:
                ref_rob = markers.lookup(res.labels)
            except ValueError as e:  # a VLM that names unmarked labels is treated as a failure
                res = VLMResult(False, res.labels, res.raw, str(e), res.latency_s, res.source)
                rec.result = res
                ref_rob = None
            if ref_rob is not None:
                rec.ref_robot = ref_rob
                ref_world = robot_to_world(ref_rob, pose)[: cfg.max_ref]
                self._score(rec, obs, markers)
                if cfg.latency_s > 0:
                    self.pending = (t + cfg.latency_s, ref_world, context)
                    self.ref, self.ref_context = None, None
                else:
                    self.ref, self.ref_context = ref_world, context
                self.queries.append(rec)
                return
        self.queries.append(rec)
        self.ref, self.ref_context = None, None
        self.next_query_t = t + cfg.retry_s

    def _extrapolate(self, pose, obs: Observation, image=None) -> bool:
        cfg = self.cfg
        pts = world_to_robot(self.ref, pose)
        if len(pts) >= 2:
            c = pts - pts.mean(0)
            d = np.linalg.svd(c, full_matrices=False)[2][0]
            if np.dot(d, pts[-1] - pts[0]) < 0:
                d = -d
        else:
            n = np.linalg.norm(pts[-1])
            if n < 1e-6:
                return False
            d = pts[-1] / n
        # a line that leaves the goal direction would drag the robot away until eq 6's gate
        # switched the reference off; such paths are re-queried instead
        g = obs.goal_robot
        if np.dot(d, g) < np.cos(cfg.max_extrapolation_angle) * np.linalg.norm(g):
            self.extrapolation_refusals += 1
            return False
        e = pts[-1] + cfg.d_extend * d
        free = bool(line_of_sight(obs.scene.local_map, e[None])[0])
        uv, inside = cfg.camera.project_ground(e[None])
        ok = free and bool(inside[0])
        if ok:
            if image is None:
                image = render_view(obs.scene.static_map, cfg.camera, obs.people_robot, cfg.person_radius)
            patch = crop_patch(image, uv[0], cfg.n_pat)
            ok = patch is not None and bool(self.classifier.is_paved(patch))
        if not ok:
            self.extrapolation_refusals += 1
            return False
        # points behind the robot no longer matter to eq 5, but two are kept for the next line fit
        ahead = pts[:, 0] > 0
        keep = self.ref[ahead] if ahead.sum() >= 2 else self.ref[-2:]
        self.ref = np.vstack([keep, robot_to_world(e, pose)[None]])[-cfg.max_ref:]
        return True

    # -- Table I scores -------------------------------------------------------------------
    def ground_truth_labels(self, pose, markers: Markers) -> np.ndarray:
        """(k, 2) robot-frame ground-truth reference path: per marker row, the marker nearest to
        the ground-truth route (if the route passes within one column spacing of it)."""
        if self.gt_world is None or len(markers.labels) == 0:
            return np.zeros((0, 2))
        route = world_to_robot(self.gt_world, np.asarray(pose, np.float64))
        out = []
        for row in sorted(set(markers.row.tolist())):
            idx = np.flatnonzero(markers.row == row)
            pts = markers.robot_xy[idx]
            d = _dist_to_polyline(pts, route)
            k = int(np.argmin(d))
            if d[k] <= self.cfg.grid.d_col:
                out.append(pts[k])
        return np.asarray(out).reshape(-1, 2)

    def _score(self, rec: QueryRecord, obs: Observation, markers: Markers):
        lm = obs.scene.static_map
        field = DistanceField(jnp.asarray(lm.clearance), jnp.asarray(lm.spec.origin_xy, jnp.float32),
                              jnp.asarray(lm.spec.cell_size, jnp.float32))
        pairs = group_pairs(obs.groups)
        rec.unacceptable = metrics.path_unacceptable(
            rec.ref_robot, field, clearance=self.cfg.robot_radius, people=obs.people_robot,
            person_gap=self.cfg.robot_radius + self.cfg.person_radius, group_pairs=pairs)
        gt = self.ground_truth_labels(rec.pose, markers)
        if len(gt):
            rec.gt_robot = gt
            rec.error = metrics.reference_path_error(rec.ref_robot, gt)
            rec.cosine = metrics.cosine_similarity(rec.ref_robot, gt)

    def stats(self) -> dict:
        """Counts and Table I scores of this episode's queries."""
        ok = [q for q in self.queries if q.result.ok]
        errs = [q.error for q in ok if q.error is not None]
        coss = [q.cosine for q in ok if q.cosine is not None]
        unacc = [q.unacceptable for q in ok if q.unacceptable is not None]
        lat = [q.result.latency_s for q in self.queries]
        return {"queries": len(self.queries), "failures": len(self.queries) - len(ok),
                "extrapolations": self.extrapolations, "extrapolation_refusals": self.extrapolation_refusals,
                "stalls": self.stalls,
                "contexts": dict(self.contexts), "ref_error": errs, "cosine": coss, "unacceptable": unacc,
                "latency_s": lat}


def _dist_to_polyline(pts: np.ndarray, poly: np.ndarray) -> np.ndarray:
    if len(poly) == 1:
        return np.linalg.norm(pts - poly[0], axis=1)
    a, b = poly[:-1], poly[1:]
    ab = b - a
    t = np.clip(np.einsum("pkd,kd->pk", pts[:, None] - a[None], ab) / np.maximum((ab * ab).sum(1), 1e-12), 0, 1)
    q = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(pts[:, None] - q, axis=-1).min(1)


__all__ = ["CoNVOI", "CoNVOIConfig", "Observation", "QueryRecord"]
