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
from .features import expert_action, observe
from .lidar import PREV_STEPS
from ..convoi.runner import GOAL_TOLERANCE, EpisodeResult, make_world
from .sc_clip import SCCLIP, SCCLIPConfig, normalize
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


N_VOTES = len(ACTIONS) + 1  # the actions, and a bucket for captions without one


def retrieve(db: jax.Array, db_actions: jax.Array, e_img: jax.Array, k: int, tau: float) -> tuple[jax.Array, jax.Array]:
    """(index into D_T of the retrieved E_T, vote vector (N_VOTES,)) for the unit E_I (D,);
    ``db`` (M, D) unit caption embeddings, ``db_actions`` (M,) int action of each caption (-1: none).

    The ``k`` captions most cosine-similar to E_I vote for their actions (weights
    ``softmax(similarity / tau)``); E_T is the caption most similar to E_I among those of the
    winning action. With k = 1 (the default) it is the thesis' plain nearest caption.

    A single nearest caption often describes the people and the layout right but carries the
    wrong action; on held-out views the vote of ~10 neighbours recovers the action more often
    (0.73 vs 0.65), though in closed loop it did not drive better, hence not the default."""
    sim = db @ e_img
    top_s, top_i = jax.lax.top_k(sim, min(max(k, 1), db.shape[0]))
    bucket = jnp.where(db_actions < 0, N_VOTES - 1, db_actions)
    votes = jnp.zeros(N_VOTES, F32).at[bucket[top_i]].add(jax.nn.softmax(top_s / tau))
    win = jnp.argmax(votes)
    return jnp.argmax(jnp.where(bucket == win, sim, -jnp.inf)), votes


@partial(jax.jit, static_argnames=("cfg", "use_image", "use_lidar", "use_text"))
def _plan(clip_p, tpn_p, tsm_p, db, db_actions, image, points, valid, goal, cfg: OliviaConfig, use_image: bool,
          use_lidar: bool, use_text: bool):
    e_i = normalize(SCCLIP(cfg.clip).apply({"params": clip_p}, image[None], method=SCCLIP.encode_image))
    j, _ = retrieve(db, db_actions, e_i[0], cfg.retrieve_k, cfg.retrieve_tau)
    e_t = db[j][None]
    trajs = TPN(cfg.tpn).apply({"params": tpn_p}, e_i, points[None], valid[None], goal[None],
                               jnp.full((1,), use_image), jnp.full((1,), use_lidar))
    logits = TSM(cfg.tsm).apply({"params": tsm_p}, e_t, trajs, jnp.full((1,), use_text))
    return trajs[0], logits[0], j, e_i[0]


@dataclass
class PlanResult:
    """trajs: (K, horizon, 3) robot frame; logits: (K,); index: k selected; caption: the
    retrieved long caption; action: its action; e_img: (D,) E_I."""

    trajs: np.ndarray
    logits: np.ndarray
    index: int
    caption: str
    action: int
    e_img: np.ndarray


class OliviaNav:
    """The planner. params: dict with ``clip``, ``tpn``, ``tsm`` pytrees; db: D_T; variant: one of
    :data:`VARIANTS`."""

    def __init__(self, params: dict, db: TextDB, cfg: OliviaConfig = OliviaConfig(), variant: str = "olivia"):
        if variant not in VARIANTS:
            raise ValueError(f"unknown variant {variant!r}; choose from {VARIANTS}")
        for k in ("clip", "tpn", "tsm"):
            if k not in params:
                raise ValueError(f"params lack the {k!r} network")
        self.params, self.db, self.cfg, self.variant = params, db, cfg, variant
        self._db = jnp.asarray(db.embeddings)
        self._db_actions = jnp.asarray(db.actions, jnp.int32)

    def with_variant(self, variant: str) -> "OliviaNav":
        return OliviaNav(self.params, self.db, self.cfg, variant)

    def plan(self, image, points, points_valid, goal) -> PlanResult:
        """Plan from one observation: image (H, W, 3) float [0, 1] or uint8; points (N, 4);
        points_valid (N,); goal (GOAL_DIM,)."""
        v = self.variant
        trajs, logits, j, e_i = _plan(self.params["clip"], self.params["tpn"], self.params["tsm"], self._db,
                                      self._db_actions, jnp.asarray(image), jnp.asarray(points, F32),
                                      jnp.asarray(points_valid), jnp.asarray(goal, F32), self.cfg,
                                      v != "no_image", v != "no_lidar", v != "no_text")
        j = int(j)
        logits = np.asarray(logits)
        return PlanResult(np.asarray(trajs), logits, int(np.argmax(logits)), self.db.captions[j],
                          int(self.db.actions[j]), np.asarray(e_i))


def run_olivia_episode(scn: Scenario, planner: OliviaNav, *, max_steps: int | None = None,
                       buffer: LLUBuffer | None = None, buffer_every: int = 5,
                       sf: pedsim.SocialForceConfig | None = None) -> EpisodeResult:
    """Drive OLiVia-Nav through ``scn`` (same loop as :func:`splatsearch.social.convoi.runner.run_episode`:
    move the robot, refusing moves into walls, then step the people, who see it). With
    ``buffer``, every ``buffer_every``-th view is stored for the LLU with its privileged scene,
    for a template captioner; the scene's action is the expert's from that state
    (:func:`~splatsearch.social.olivia.features.expert_action`). ``plan_ms`` is the mean wall-clock
    per planning cycle."""
    cfg = planner.cfg
    sf = sf or pedsim.SocialForceConfig(dt=scn.dt, robot_radius=ROBOT_RADIUS)
    caps, valid = scn.padded_capsules()
    caps, valid = jnp.asarray(caps), jnp.asarray(valid)
    field = scn.field()
    path = scn.global_path()
    seed_key = jax.random.PRNGKey(scn.seed)
    n = scn.max_steps if max_steps is None else int(max_steps)
    pose = np.asarray(scn.start, np.float32)
    peds = scn.peds
    fstate = follower_init()
    poses, people, cmds, contacts = [pose], [np.asarray(peds.pos)], [], []
    ped_contacts = wall_hits = 0
    reached = False
    traj_world = None
    plan_s, n_plans = 0.0, 0
    from ..convoi.runner import REFERENCE

    expert_world = make_world(scn, "expert") if buffer is not None and REFERENCE == "expert" else None
    for t in range(n):
        if t % cfg.replan_every == 0 or traj_world is None:
            tp = max(len(poses) - 1 - PREV_STEPS, 0)
            t0 = time.perf_counter()
            obs = observe(scn, pose, people[-1], poses[tp], people[tp], path)
            res = planner.plan(obs.image, obs.points, obs.points_valid, obs.goal)
            tr = res.trajs[res.index]
            traj_world = np.vstack([pose[None, :2], robot_to_world(tr[:, :2].astype(np.float64), pose.astype(np.float64))])
            plan_s += time.perf_counter() - t0
            n_plans += 1
            if buffer is not None and not buffer.full and (t // cfg.replan_every) % buffer_every == 0:
                # the captioner judges the view as a VLM would: the action the robot should
                # take there (the expert's), not the one it chose, which would only teach the
                # encoders the planner's own mistakes
                act = expert_action(scn, pose, cmds[-1] if cmds else np.zeros(2, np.float32), peds, t, expert_world)
                buffer.add(obs.image, caption_scene(scn, pose, people[-1], np.asarray(peds.vel), act), obs)
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
