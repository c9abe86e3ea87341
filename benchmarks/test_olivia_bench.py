"""OLiVia-Nav planning rate (target >= 5 Hz on 2 CPU cores, thesis 3.5.1.2).

One planning cycle = sensors (egocentric render + two LiDAR sweeps + goal) + SC-CLIP image
encoder + D_T retrieval + TPN + TSM, and one PID step; measured as trained ("offline") and after an
LLU update ("after_llu": a second image encoding for the TPN, 50 more D_T entries). Uses the trained checkpoint at
``$OLIVIA_CHECKPOINT`` (default ``runs/olivia/olivia.npz``) when it exists, else freshly
initialised networks of the same size (the rate does not depend on the weights).

    python -m pytest benchmarks/test_olivia_bench.py --benchmark-enable
"""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from splatsearch.social.convoi.controller import follow_step, follower_init
from splatsearch.social.convoi.geometry import robot_to_world
from splatsearch.social.olivia.llu import TextDB, add_view_entries
from splatsearch.social.convoi.perception import visible_people
from splatsearch.social.olivia.planner import OliviaConfig, OliviaNav, consistency_cost, safety_cost
from splatsearch.social.olivia.features import observe
from splatsearch.social.convoi.scenarios import make_scenario


def _planner() -> OliviaNav:
    path = os.environ.get("OLIVIA_CHECKPOINT", "runs/olivia/olivia.npz")
    if os.path.exists(path):
        from splatsearch.social.olivia.train import load_planner

        return load_planner(path)
    from splatsearch.social.olivia import sc_clip
    from splatsearch.social.olivia import tpn
    from splatsearch.social.olivia import tsm

    cfg = OliviaConfig()
    k = jax.random.split(jax.random.PRNGKey(0), 3)
    params = {"clip": sc_clip.init_sc_clip(k[0], cfg.clip), "tpn": tpn.init_tpn(k[1], cfg.tpn),
              "tsm": tsm.init_tsm(k[2], cfg.tsm)}
    rng = np.random.default_rng(0)
    emb = rng.normal(size=(1000, cfg.clip.embed)).astype(np.float32)
    db = TextDB(emb / np.linalg.norm(emb, axis=1, keepdims=True), [f"c{i}" for i in range(1000)],
                np.zeros(1000, np.int32))
    return OliviaNav(params, db, cfg)


def _after_update(planner: OliviaNav) -> OliviaNav:
    """The planner after one LLU update: a second image encoder (the TPN keeps the one it was
    trained with) and 50 view-keyed D_T entries."""
    rng = np.random.default_rng(1)
    e = rng.normal(size=(50, planner.cfg.clip.embed)).astype(np.float32)
    db = add_view_entries(planner.db, e, e[::-1], ["you should yield"] * 50)
    return OliviaNav(dict(planner.params, clip_tpn=planner.params["clip"]), db, planner.cfg)


@pytest.fixture(scope="module", params=["offline", "after_llu"])
def setup(request):
    scn = make_scenario("static_groups", 1000)
    planner = _planner()
    if request.param == "after_llu":
        planner = _after_update(planner)
    pose = np.asarray(scn.start, np.float32)
    people = np.asarray(scn.peds.pos)
    path = scn.global_path()
    caps, valid = (jnp.asarray(a) for a in scn.padded_capsules())
    act = jnp.asarray(scn.peds.active)

    def cycle():
        obs = observe(scn, pose, people, pose, people, path)
        res = planner.plan(obs.image, obs.points, obs.points_valid, obs.goal)
        # the selection's costs, as in run_olivia_episode (against the same plan as "followed")
        cand = np.stack([robot_to_world(q[:, :2].astype(np.float64), pose.astype(np.float64)) for q in res.trajs])
        prev = np.vstack([pose[None, :2], cand[res.index]])
        seen = np.asarray(visible_people(jnp.asarray(pose), jnp.asarray(people), act, caps, valid))
        score = (res.logits - planner.cfg.consistency * consistency_cost(cand, prev, 0.2)
                 - planner.cfg.safety * safety_cost(cand, people[seen], np.zeros_like(people[seen]),
                                                    planner.cfg.safety_margin))
        traj = np.vstack([pose[None, :2], cand[int(np.argmax(score))]])
        cmd, _ = follow_step(planner.cfg.follower, follower_init(), jnp.asarray(pose), jnp.asarray(traj, jnp.float32),
                             0.1)
        return np.asarray(cmd)

    cycle()  # compile
    return cycle


def test_planning_cycle(benchmark, setup):
    cmd = benchmark(setup)
    assert cmd.shape == (2,) and np.all(np.isfinite(cmd))
    if benchmark.stats is not None:
        benchmark.extra_info["hz"] = 1.0 / benchmark.stats.stats.mean
