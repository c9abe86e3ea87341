"""OLiVia-Nav, the planner (thesis Fig. 1): SCM encoders -> TPN -> TSM -> NC.

One planning cycle (:meth:`OliviaNav.plan`, one jitted function for the networks):

1. F_I embeds the egocentric view: E_I.
2. E_T is retrieved from the text database D_T by cosine similarity to E_I (thesis 3.2.1.1;
   :func:`retrieve`, optionally with a vote of the nearest captions on the action).
3. The TPN plans K trajectories from E_I, the LiDAR sweeps and the goal (eq 1).
4. The TSM scores them with E_T and the best one is τ* (eq 7).
5. The NC (the social module's PID follower) tracks τ* until the next plan.

:func:`run_olivia_episode` closes the loop in a scenario among the simulated people and returns
the social module's :class:`~splatsearch.social.convoi.runner.EpisodeResult`, so that the same metrics
apply to OLiVia-Nav, DWA, CoNVOI and the expert. The ablations switch E_I (TPN), E_L (TPN) or
E_T (TSM) off.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from ..convoi import pedsim
from ..convoi.controller import FollowerConfig, follow_step, follower_init
from ..convoi.dwa import step_unicycle
from ..convoi.geometry import F32, field_lookup, robot_to_world
from .llu import LLUBuffer, TextDB
from .captions import ACTIONS, caption_scene
from .features import HORIZON, KEEP_THRESHOLD, expert_action, observe
from ..convoi.perception import visible_people
from .lidar import PREV_STEPS
from .person_key import person_distance2, person_state
from .route import PerceivedRoute
from ..convoi.runner import GOAL_TOLERANCE, EpisodeResult, make_world
from .sc_clip import SCCLIP, SCCLIPConfig, normalize
from .selection import (WALL_MARGIN, consistency_cost, oncoming_count, oncoming_mask, safety_cost,  # noqa: F401
                        selection_scores, side_cost)
from ..convoi.scenarios import ROBOT_RADIUS, Scenario
from .tpn import TPN, TPNConfig
from .tsm import TSM, TSMConfig


VARIANTS = ("olivia", "no_image", "no_text", "no_lidar")
VARIANT_LABELS = {"olivia": "OLiVia-Nav", "no_image": "OLiVia-Nav w/o E_I", "no_text": "OLiVia-Nav w/o E_T",
                  "no_lidar": "OLiVia-Nav w/o E_L"}


@dataclass(frozen=True)
class OliviaConfig:
    """The three networks' configurations, the NC's, and the replanning period (sim steps)."""

    clip: SCCLIPConfig = SCCLIPConfig()
    tpn: TPNConfig = TPNConfig()
    tsm: TSMConfig = TSMConfig()
    follower: FollowerConfig = FollowerConfig()
    replan_every: int = 2  # 5 Hz at dt = 0.1 s (the thesis' planning rate)
    retrieve_k: int = 1  # D_T neighbours voting on the retrieved E_T's action (1: the thesis' nearest caption)
    retrieve_tau: float = 0.05  # temperature of the votes' softmax over cosine similarities
    vote_memory: float = 0.0  # decay per plan of the accumulated retrieval votes (0: each view alone)
    score_weight: float = 1.0  # weight of the TPN's mode log-probabilities added to the TSM's (0: TSM alone)
    consistency: float = 30.0  # 1/m²: penalty on a plan's mean squared distance from the one being followed
    safety: float = 30.0  # 1/m²: penalty on a plan's intrusion into the people's predicted space (0: off)
    safety_margin: float = 0.45  # m, edge to edge: the intimate zone a plan must keep from everyone seen
    pass_right: float = 0.0  # penalty on a plan that lets a head-on person go by on the robot's right (0: off)
    text_gate: float = 0.9  # E_T is used only when the retrieved caption's cosine similarity to E_I reaches it
    view_gate: float = 0.95  # the same for D_T entries an LLU update keyed by their views' E_I (image to image)
    arrive_radius: float = 1.0  # m: within it the NC drives straight at the goal (0: off)
    # while someone walks at the robot head-on (selection.oncoming_mask): the consistency cost does
    # not charge a plan's deviation to the right of the followed one (yielding), and, when
    # cross_tau > 0 (s), the safety cost lets the part of their velocity across the line to the
    # robot decay with that time constant. Off by default: on doorways where the person keeps
    # walking diagonally past the door, that forecast sent the robot into their path (stop 39)
    oncoming_yield: bool = True
    cross_tau: float = 0.0
    # 1/s: the safety cost's forecast lets people ahead make way for the robot at this rate
    # (forecast.reactive_forecast; 0: they walk on at constant velocity). Off by default: on dev
    # seeds it helped dynamic groups of one training and hurt others (stop 41)
    people_react: float = 0.0
    oncoming_time: float = 4.0  # s: a person counts as head-on when it can meet the robot within this time
    route_fallback: bool = True  # when every plan runs into the map, the NC follows the static route
    # m: the route (goal features, fallback) keeps this far from people standing still and never
    # crosses a standing group, as the walker's does, reading who stands where from the scene
    # (privileged; 0: off)
    route_berth: float = 0.0
    # m: the same berth around the standing people the robot has perceived (route.PerceivedRoute:
    # in line of sight within sensing range, measured slower than route.STAND_SPEED); used when
    # route_berth is 0 (0: the walls-only shortest path); training data use the same route
    # (TrainConfig.perceived_berth)
    perceived_berth: float = 0.8
    # D_T's view entries are also keyed by the nearest perceived person's state (person_key.py:
    # range, bearing, closing speed, lateral offset). False: the thesis' image-only key
    person_key: bool = False
    person_weight: float = 0.05  # ranking: image cosine minus this x the scaled squared person distance d2
    person_gate: float = 1.0  # a view entry's E_T is used only when d2 <= this (and the image cosine passes view_gate)
    # > 0: a view entry whose person key matches the perceived person (both seen, d2 <= person_gate)
    # ranks above every other entry and needs only this image cosine (0: view_gate as any view entry)
    person_view_gate: float = 0.0

    def __post_init__(self):
        for name in ("cross_tau", "people_react"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and v >= 0):
                raise ValueError(f"OliviaConfig.{name} must be a number >= 0, got {v!r}")


N_VOTES = len(ACTIONS) + 1  # the actions, and a bucket for captions without one


def retrieve(db: jax.Array, db_actions: jax.Array, e_img: jax.Array, k: int, tau: float,
             prior: jax.Array | None = None, penalty: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:
    """(index into D_T of the retrieved E_T, vote vector (N_VOTES,)) for the unit E_I (D,);
    ``db`` (M, D) D_T's unit retrieval keys (:attr:`TextDB.key_matrix`: the caption embeddings,
    or for an LLU update's entries the E_I of their views), ``db_actions`` (M,) int action of each
    caption (-1: none).

    The ``k`` captions most cosine-similar to E_I vote for their actions (weights
    ``softmax(similarity / tau)``); E_T is the caption most similar to E_I among those of the
    winning action. With k = 1 (the default) it is the thesis' plain nearest caption.

    A single nearest caption often describes the people and the layout right but carries the
    wrong action; on held-out views the vote of ~10 neighbours recovers the action more often
    (0.73 vs 0.65), though in closed loop it did not drive better, hence not the default.

    ``prior`` (N_VOTES,): votes carried over from the previous views (decayed by the caller), added
    before the winning action is chosen; the returned vector includes them.

    ``penalty`` (M,): subtracted from the similarities before ranking (the person part of the
    key, :func:`person_penalty`; None: none)."""
    sim = db @ e_img
    if penalty is not None:
        sim = sim - penalty
    top_s, top_i = jax.lax.top_k(sim, min(max(k, 1), db.shape[0]))
    bucket = jnp.where(db_actions < 0, N_VOTES - 1, db_actions)
    votes = jnp.zeros(N_VOTES, F32).at[bucket[top_i]].add(jax.nn.softmax(top_s / tau))
    if prior is not None:
        votes = votes + prior
    win = jnp.argmax(votes)
    return jnp.argmax(jnp.where(bucket == win, sim, -jnp.inf)), votes


@partial(jax.jit, static_argnames=("cfg", "use_image", "use_lidar", "use_text"))
def _plan(clip_p, tpn_clip_p, tpn_p, tsm_p, db, keys, gates, db_actions, image, points, valid, goal, prior,
          penalty, person_ok, cfg: OliviaConfig, use_image: bool, use_lidar: bool, use_text: bool):
    e_i = normalize(SCCLIP(cfg.clip).apply({"params": clip_p}, image[None], method=SCCLIP.encode_image))
    # the TPN reads E_I from the encoder it was trained with (an LLU update moves only retrieval's)
    e_i_tpn = e_i if tpn_clip_p is None else normalize(
        SCCLIP(cfg.clip).apply({"params": tpn_clip_p}, image[None], method=SCCLIP.encode_image))
    j, votes = retrieve(keys, db_actions, e_i[0], cfg.retrieve_k, cfg.retrieve_tau, cfg.vote_memory * prior, penalty)
    e_t = db[j][None]
    sim = keys[j] @ e_i[0]
    # a caption retrieved with low similarity describes another scene (its action is right about
    # half the time on held-out views); the TSM then ranks without E_T, as trained with text dropout
    use_text = jnp.asarray(use_text) & (sim >= gates[j]) & person_ok[j]
    trajs, scores = TPN(cfg.tpn).apply({"params": tpn_p}, e_i_tpn, points[None], valid[None], goal[None],
                                       jnp.full((1,), use_image), jnp.full((1,), use_lidar), with_scores=True)
    logits = TSM(cfg.tsm).apply({"params": tsm_p}, e_t, trajs, jnp.full((1,), use_text))
    logits = select_logits(logits, scores, cfg.score_weight)
    return trajs[0], logits[0], j, e_i[0], votes, sim, use_text


def person_penalty(db: TextDB, person: np.ndarray | None, cfg: OliviaConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(penalty (M,), ok (M,) bool, image-cosine gate (M,)) of D_T's entries for the perceived person state ``person``
    (PERSON_DIM,) (:func:`~splatsearch.social.olivia.person_key.person_state`; NaN: nobody ahead).
    Only view entries with ``db.persons`` take part, and only with ``cfg.person_key``: their
    ranking loses ``cfg.person_weight`` x d2 (capped at 100) and they pass the gate only when
    d2 <= ``cfg.person_gate``; nobody ahead matches nobody ahead (d2 0) and no person state
    (inf). Every other entry: penalty 0, ok. The gate is ``view_gate`` for view entries and
    ``text_gate`` for the others; with ``cfg.person_view_gate`` > 0 a view entry matched by a
    person actually seen (d2 <= person_gate) gets that gate and a penalty lowered by 1 (it ranks
    first: image cosines lie in [-1, 1])."""
    m = len(db.captions)
    is_view = np.any(db.key_matrix != db.embeddings, axis=1)
    gate = np.where(is_view, cfg.view_gate, cfg.text_gate).astype(np.float32)
    if not cfg.person_key or db.persons is None or person is None:
        return np.zeros(m, np.float32), np.ones(m, bool), gate
    keys = np.asarray(db.persons, np.float32)
    s = np.asarray(person, np.float32)
    d2 = person_distance2(s, keys)
    none_both = np.all(np.isnan(keys), 1) & bool(np.all(np.isnan(s)))
    d2 = np.where(none_both, 0.0, d2)
    pen = np.where(is_view, cfg.person_weight * np.minimum(d2, 100.0), 0.0).astype(np.float32)
    ok = ~is_view | (d2 <= cfg.person_gate)
    if cfg.person_view_gate > 0 and not np.all(np.isnan(s)):
        matched = is_view & ~np.all(np.isnan(keys), 1) & (d2 <= cfg.person_gate)
        pen = np.where(matched, pen - 1.0, pen).astype(np.float32)
        gate = np.where(matched, cfg.person_view_gate, gate).astype(np.float32)
    return pen, ok, gate


def select_logits(tsm_logits: jax.Array, tpn_scores: jax.Array, score_weight: float) -> jax.Array:
    """The plan selection's log-scores (..., K): the TSM's log-probabilities (eq 7) plus
    ``score_weight`` x the TPN's mode log-probabilities. The TSM ranks the plans by E_T alone and
    follows the retrieved caption's action; the TPN's scores come from the LiDAR (both sweeps,
    so the people's motion), the goal and E_I, and decide among plans the caption does not
    separate, or against a caption D_T retrieved wrongly."""
    out = jax.nn.log_softmax(tsm_logits, -1)
    if score_weight:
        out = out + score_weight * jax.nn.log_softmax(tpn_scores, -1)
    return out


@dataclass
class PlanResult:
    """trajs: (K, horizon, 3) robot frame; logits: (K,); index: k selected; caption: the
    retrieved long caption; action: its action; e_img: (D,) E_I; votes: (N_VOTES,) the
    retrieval's accumulated action votes (the next plan's ``prior``); similarity: cosine of E_I
    and the retrieved E_T (E_T is used when it reaches ``cfg.text_gate``); text_used: whether it was."""

    trajs: np.ndarray
    logits: np.ndarray
    index: int
    caption: str
    action: int
    e_img: np.ndarray
    votes: np.ndarray | None = None
    similarity: float = 1.0
    text_used: bool = True  # E_T reached the TSM (the variant has text and the gate passed)
    retrieved: int = -1  # index into D_T of the retrieved E_T


class OliviaNav:
    """The planner. params: dict with ``clip``, ``tpn``, ``tsm`` pytrees, and after an LLU update
    ``clip_tpn``: the SC-CLIP the TPN was trained with, which gives the TPN its E_I while the
    updated ``clip`` gives retrieval's (without it, ``clip`` gives both); db: D_T; variant: one of
    :data:`VARIANTS`."""

    def __init__(self, params: dict, db: TextDB, cfg: OliviaConfig = OliviaConfig(), variant: str = "olivia"):
        if variant not in VARIANTS:
            raise ValueError(f"unknown variant {variant!r}; choose from {VARIANTS}")
        for k in ("clip", "tpn", "tsm"):
            if k not in params:
                raise ValueError(f"params lack the {k!r} network")
        self.params, self.db, self.cfg, self.variant = params, db, cfg, variant
        self._db = jnp.asarray(db.embeddings)
        self._keys = jnp.asarray(db.key_matrix)
        self._db_actions = jnp.asarray(db.actions, jnp.int32)

    def with_variant(self, variant: str) -> "OliviaNav":
        return OliviaNav(self.params, self.db, self.cfg, variant)

    def plan(self, image, points, points_valid, goal, prior=None, person=None) -> PlanResult:
        """Plan from one observation: image (H, W, 3) float [0, 1] or uint8; points (N, 4);
        points_valid (N,); goal (GOAL_DIM,); prior: (N_VOTES,) the previous plan's ``votes``
        (used with ``cfg.vote_memory`` > 0; None: none); person: (PERSON_DIM,) the perceived
        nearest person's state (:func:`~splatsearch.social.olivia.person_key.person_state`),
        retrieval's person key with ``cfg.person_key`` (None: the image-only key)."""
        v = self.variant
        prior = jnp.zeros(N_VOTES, F32) if prior is None else jnp.asarray(prior, F32)
        p = self.params
        # entries keyed by a view (an LLU update's) are gated on image-to-image similarity
        pen, ok, gates = person_penalty(self.db, person, self.cfg)
        trajs, logits, j, e_i, votes, sim, used = _plan(p["clip"], p.get("clip_tpn"), p["tpn"], p["tsm"], self._db, self._keys,
                                                  jnp.asarray(gates), self._db_actions, jnp.asarray(image),
                                                  jnp.asarray(points, F32), jnp.asarray(points_valid),
                                                  jnp.asarray(goal, F32), prior, jnp.asarray(pen), jnp.asarray(ok),
                                                  self.cfg, v != "no_image",
                                                  v != "no_lidar", v != "no_text")
        j = int(j)
        logits = np.asarray(logits)
        return PlanResult(np.asarray(trajs), logits, int(np.argmax(logits)), self.db.captions[j],
                          int(self.db.actions[j]), np.asarray(e_i), np.asarray(votes), float(sim), bool(used), j)


def route_ahead(path: np.ndarray, xy: np.ndarray, n: int, step: float = 0.24) -> np.ndarray:
    """(1 + n, 2) world: ``xy`` (2,), then ``n`` points of the route ``path`` (M, 2) every
    ``step`` m (0.6 m/s x 0.4 s) from the route point nearest to ``xy`` (held at its end)."""
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    i = int(np.argmin(np.linalg.norm(path - np.asarray(xy, np.float64), axis=1)))
    q = np.minimum(s[i] + step * np.arange(1, n + 1), s[-1])
    pts = np.stack([np.interp(q, s, path[:, 0]), np.interp(q, s, path[:, 1])], -1)
    return np.vstack([np.asarray(xy, np.float64)[None], pts])


def run_olivia_episode(scn: Scenario, planner: OliviaNav, *, max_steps: int | None = None,
                       buffer: LLUBuffer | None = None, buffer_every: int = 5,
                       sf: pedsim.SocialForceConfig | None = None, trace: list | None = None,
                       reference_shift=None, caption_keep: float = KEEP_THRESHOLD) -> EpisodeResult:
    """Drive OLiVia-Nav through ``scn`` (same loop as :func:`splatsearch.social.convoi.runner.run_episode`:
    move the robot, refusing moves into walls, then step the people, who see it). With
    ``buffer``, every ``buffer_every``-th view is stored for the LLU with its privileged scene,
    for a template captioner; the scene's action is the expert's from that state
    (:func:`~splatsearch.social.olivia.features.expert_action`). ``plan_ms`` is the mean wall-clock
    per planning cycle. ``trace``: a list that gets, per plan, the step ``t``, the ``pose``, the
    world plans ``cand``, the networks' ``logits``, the retrieved caption's ``similarity`` and
    ``action`` (and its index ``retrieved`` in D_T), the ``route`` in use,
    :func:`selection_scores`' parts and the ``index`` selected; and what re-scoring the same
    state needs: the observation ``obs``, the people seen (``seen_people``, ``seen_vel``), the
    followed plan ``prev_world`` made ``elapsed`` s ago, the map ``clearance``, and the
    simulator's people ``peds`` and the robot's last command ``cmd`` (for a reference rollout
    from that state). ``reference_shift``: optional callable step -> the lateral shift (m) the
    reference walker's own episode holds at that step; the captioner's walker is forked with
    it (see :func:`~splatsearch.social.olivia.features.expert_action`), else with none.
    ``caption_keep`` (m): the side threshold of the buffer scenes' action (default the training
    data's, :data:`~splatsearch.social.olivia.features.KEEP_THRESHOLD`)."""
    cfg = planner.cfg
    sf = sf or pedsim.SocialForceConfig(dt=scn.dt, robot_radius=ROBOT_RADIUS)
    caps, valid = scn.padded_capsules()
    caps, valid = jnp.asarray(caps), jnp.asarray(valid)
    act = jnp.asarray(scn.peds.active)
    field = scn.field()
    path = scn.global_path(avoid_standing=cfg.route_berth) if cfg.route_berth > 0 else scn.global_path()
    route = PerceivedRoute(scn, cfg.perceived_berth if cfg.route_berth <= 0 else 0.0)
    seed_key = jax.random.PRNGKey(scn.seed)
    n = scn.max_steps if max_steps is None else int(max_steps)
    pose = np.asarray(scn.start, np.float32)
    peds = scn.peds
    fstate = follower_init()
    poses, people, cmds, contacts = [pose], [np.asarray(peds.pos)], [], []
    ped_contacts = wall_hits = 0
    reached = False
    traj_world = None
    votes = None
    since = 0
    plan_s, n_plans = 0.0, 0
    ever_seen = np.zeros(len(np.asarray(scn.peds.active)), bool)  # whom the robot has perceived so far
    from ..convoi.runner import REFERENCE

    expert_world = make_world(scn, "expert") if buffer is not None and REFERENCE == "expert" else None
    for t in range(n):
        if t % cfg.replan_every == 0 or traj_world is None:
            tp = max(len(poses) - 1 - PREV_STEPS, 0)
            t0 = time.perf_counter()
            seen = np.asarray(visible_people(jnp.asarray(pose), jnp.asarray(people[-1]), act, caps, valid))
            ever_seen |= seen
            vel = (people[-1] - people[tp]) / max((len(poses) - 1 - tp) * scn.dt, scn.dt)
            if route.berth > 0:
                path = route.update(people[-1], vel, seen, t * scn.dt,
                                    measured=len(poses) - 1 - tp >= PREV_STEPS)
            obs = observe(scn, pose, people[-1], poses[tp], people[tp], path)
            # what the LiDAR measures of the nearest person (retrieval's person key; perception, not the scene)
            pstate = person_state(pose, people[-1][seen], vel[seen])
            res = planner.plan(obs.image, obs.points, obs.points_valid, obs.goal, votes, pstate)
            votes = res.votes
            cand = np.stack([robot_to_world(q[:, :2].astype(np.float64), pose.astype(np.float64)) for q in res.trajs])
            clr = np.asarray(field_lookup(field, jnp.asarray(cand, F32))) if cfg.safety > 0 else None
            parts = selection_scores(res.logits, cand, pose, traj_world, since * scn.dt, people[-1][seen], vel[seen],
                                     clr, cfg)
            score = parts["score"]
            k = int(np.argmax(score))
            if trace is not None:
                trace.append({"t": t, "pose": pose.copy(), "cand": cand, "trajs": res.trajs, "logits": np.asarray(res.logits),
                              "similarity": res.similarity, "action": res.action, "text_used": res.text_used,
                              "retrieved": res.retrieved, "route": path, "index": k, "obs": obs, "person": pstate,
                              "seen_people": people[-1][seen], "seen_vel": vel[seen], "prev_world": traj_world,
                              "elapsed": since * scn.dt, "clearance": clr, "peds": peds,
                              "cmd": cmds[-1] if cmds else np.zeros(2, np.float32)} | parts)
            traj_world = np.vstack([pose[None, :2], cand[k]])
            if cfg.route_fallback and clr is not None and np.all(parts["map"] > 0):
                # every plan runs into the map (a door post ahead): the NC follows the static
                # route instead; following the least bad plan, it pushed into the post for good
                traj_world = route_ahead(path, pose[:2], HORIZON)
            if cfg.arrive_radius > 0 and np.linalg.norm(pose[:2] - scn.goal) < cfg.arrive_radius:
                # the last metre: straight at the goal (plans trained on paths that end there
                # do not turn back to a goal overshot)
                traj_world = np.linspace(pose[:2], np.asarray(scn.goal, np.float64), HORIZON + 1)
            since = 0
            plan_s += time.perf_counter() - t0
            n_plans += 1
            if buffer is not None and not buffer.full and (t // cfg.replan_every) % buffer_every == 0:
                # the captioner judges the view as a VLM would: the action the robot should
                # take there (the expert's), not the one it chose, which would only teach the
                # encoders the planner's own mistakes
                def scene(pose=pose, cmd=cmds[-1] if cmds else np.zeros(2, np.float32), peds=peds, t=t,
                          people_now=people[-1], known=ever_seen.copy()):
                    # a walker forked with no side chosen can undo the reference's sidestep at the
                    # moment it begins (its change cost flips it): fork the one that chose it
                    off = reference_shift(t) if reference_shift is not None else None
                    # the perceiving walker forked here knows whom the robot has perceived so far
                    act = expert_action(scn, pose, cmd, peds, t, expert_world, offset=off, seen=known, keep=caption_keep)
                    return caption_scene(scn, pose, people_now, np.asarray(peds.vel), act)

                seen = np.asarray(visible_people(jnp.asarray(pose), jnp.asarray(people[-1]), act, caps, valid))
                vel = (people[-1] - people[tp]) / max((len(poses) - 1 - tp) * scn.dt, scn.dt)
                buffer.add(obs.image, scene if buffer.lazy else scene(), obs,
                           oncoming_count(pose, people[-1][seen], vel[seen]), scn.seed, pstate)
        since += 1
        cmd, fstate = follow_step(cfg.follower, fstate, jnp.asarray(pose), jnp.asarray(traj_world, F32), scn.dt)
        new_pose = np.asarray(step_unicycle(jnp.asarray(pose), cmd, scn.dt))
        if float(field_lookup(field, jnp.asarray(new_pose[:2]))) < ROBOT_RADIUS:
            new_pose, cmd = pose, jnp.zeros(2, F32)
            wall_hits += 1
        rv = float(cmd[0]) * np.array([np.cos(new_pose[2]), np.sin(new_pose[2])], np.float32)
        peds, info = pedsim.step(peds, caps, valid, jnp.asarray(new_pose[:2]), jnp.asarray(rv),
                                 pedsim.step_key(seed_key, t), sf)
        pose = new_pose.astype(np.float32)
        poses.append(pose)
        people.append(np.asarray(peds.pos))
        cmds.append(np.asarray(cmd))
        contacts.append(int(np.asarray(info.robot_contact).sum()))
        ped_contacts += int(info.ped_contacts)
        if np.linalg.norm(pose[:2] - scn.goal) < GOAL_TOLERANCE:
            reached = True
            break
    T = len(cmds)
    return EpisodeResult(scn.name, f"olivia:{planner.variant}", scn.seed, np.asarray(poses),
                         np.asarray(cmds).reshape(T, 2), np.asarray(people), np.asarray(scn.peds.active),
                         np.zeros((T, len(np.asarray(scn.peds.active))), bool), np.arange(T + 1) * scn.dt,
                         np.asarray(scn.goal), np.asarray(scn.start), reached, 0, np.asarray(contacts), wall_hits,
                         ped_contacts, 1e3 * plan_s / max(n_plans, 1), {}, scn.dt)
