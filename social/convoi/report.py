"""Evaluate planners on the scenarios and tabulate the results like the papers' tables.

For each scenario and seed, the expert runs first; its trajectory is the "teleoperation" ground
truth that MSE, Hausdorff and Fréchet compare with, and the route CoNVOI's ground-truth reference
paths follow. Then every method runs on the same seeded scenario.

Tables (means over seeds):

* thesis Table I style: MSE (m²), Hausdorff (m), PSV (s, edge-to-edge gap < ``psv_zone``), plus
  success rate, collisions and the smallest edge-to-edge distance to a person;
* CoNVOI Table II style: Fréchet (m), normalised trajectory length, mean velocity (m/s);
* CoNVOI Table I style (CoNVOI only): reference-path error (m), cosine similarity, share of
  unacceptable paths, VLM inference time (s), queries and extrapolations per episode.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import metrics
from .runner import EpisodeResult, run_episode
from .scenarios import PERSON_RADIUS, ROBOT_RADIUS, Scenario, make_scenario

METHOD_LABELS = {"expert": "Expert (teleop. reference)", "dwa": "DWA", "convoi": "CoNVOI + DWA"}


@dataclass
class EpisodeMetrics:
    """The metrics of one episode (see the module doc for units)."""

    scenario: str
    method: str
    seed: int
    mse: float
    hausdorff: float
    frechet: float
    psv: float
    norm_length: float
    mean_velocity: float
    min_distance: float
    collisions: int
    success: bool
    reached: bool
    steps: int
    fallbacks: int
    plan_ms: float
    convoi: dict = field(default_factory=dict)


def episode_metrics(res: EpisodeResult, expert: EpisodeResult, scn: Scenario, psv_zone: float = 0.25) -> EpisodeMetrics:
    """All trajectory metrics of ``res`` against the expert's trajectory."""
    traj = res.robot[:, :2]
    ref = expert.robot[:, :2]
    valid = np.broadcast_to(res.active, res.people.shape[:2])
    kw = {"valid": valid, "robot_radius": ROBOT_RADIUS, "person_radius": PERSON_RADIUS}
    coll = metrics.collision_count(traj, res.people, valid, ROBOT_RADIUS, PERSON_RADIUS, field=scn.field())
    return EpisodeMetrics(
        res.scenario, res.planner, res.seed, metrics.mse(traj, ref), metrics.hausdorff(traj, ref),
        metrics.frechet(traj, ref), metrics.psv_duration(traj, res.people, res.dt, psv_zone, **kw),
        metrics.normalized_length(traj), metrics.mean_velocity(traj, res.dt),
        metrics.min_distance_to_people(traj, res.people, **kw), coll, metrics.success(res.reached, coll),
        bool(res.reached), len(res.cmds), int(res.fallbacks), float(res.plan_ms), dict(res.convoi))


def evaluate(scenarios, seeds, methods=("dwa", "convoi"), *, vlm=None, convoi_cfg=None, classifier=None,
             observer_factory=None, progress=None) -> list[EpisodeMetrics]:
    """Run the expert and ``methods`` on every scenario x seed; returns one row per episode
    (the expert's rows included). ``vlm`` defaults to the rule-based one. ``observer_factory(scn,
    method, convoi)`` may return a per-step observer (the live viewer). ``progress(text)`` is called
    before each episode."""
    from .pipeline import CoNVOI, CoNVOIConfig
    from .vlm import RuleBasedVLM

    vlm = vlm if vlm is not None else RuleBasedVLM()
    rows = []
    for name in scenarios:
        for seed in seeds:
            scn = make_scenario(name, seed)
            if progress:
                progress(f"{name} seed {seed}: expert")
            obs = observer_factory(scn, "expert", None) if observer_factory else None
            expert = run_episode(scn, "expert", observer=obs)
            rows.append(episode_metrics(expert, expert, scn))
            for m in methods:
                if progress:
                    progress(f"{name} seed {seed}: {m}")
                cv = None
                if m == "convoi":
                    cv = CoNVOI(vlm, classifier, convoi_cfg or CoNVOIConfig())
                    cv.set_ground_truth(expert.robot)
                obs = observer_factory(scn, m, cv) if observer_factory else None
                res = run_episode(scn, m, convoi=cv, observer=obs)
                rows.append(episode_metrics(res, expert, scn))
    return rows


def _mean(xs):
    xs = [x for x in xs if x is not None and np.isfinite(x)]
    return float(np.mean(xs)) if xs else float("nan")


def summarise(rows: list[EpisodeMetrics]) -> list[dict]:
    """One dict per (scenario, method) with the seed means of every metric."""
    out = []
    keys = []
    for r in rows:
        if (r.scenario, r.method) not in keys:
            keys.append((r.scenario, r.method))
    for scen, meth in keys:
        rs = [r for r in rows if r.scenario == scen and r.method == meth]
        d = {"scenario": scen, "method": meth, "episodes": len(rs)}
        for k in ("mse", "hausdorff", "frechet", "psv", "norm_length", "mean_velocity", "min_distance", "collisions",
                  "fallbacks", "plan_ms"):
            d[k] = _mean([getattr(r, k) for r in rs])
        d["success"] = _mean([float(r.success) for r in rs])
        if meth == "convoi":
            cs = [r.convoi for r in rs]
            d["ref_error"] = _mean([x for c in cs for x in c.get("ref_error", [])])
            d["cosine"] = _mean([x for c in cs for x in c.get("cosine", [])])
            d["unacceptable"] = metrics.fraction_unacceptable([x for c in cs for x in c.get("unacceptable", [])])
            d["latency_s"] = _mean([x for c in cs for x in c.get("latency_s", [])])
            d["queries"] = _mean([c.get("queries", 0) for c in cs])
            d["failures"] = _mean([c.get("failures", 0) for c in cs])
            d["extrapolations"] = _mean([c.get("extrapolations", 0) for c in cs])
        out.append(d)
    return out


def tables(summary: list[dict], n_seeds: int):
    """Three rich tables (thesis Table I style, CoNVOI Table II style, CoNVOI Table I style)."""
    from rich.table import Table

    def f(x, nd=3):
        return "-" if x is None or not np.isfinite(x) else f"{x:.{nd}f}"

    t1 = Table(title=f"Social navigation vs the expert (thesis Table I style), mean of {n_seeds} seed(s)")
    for c in ("Scenario", "Method", "MSE ↓", "Haus ↓", "PSV (s) ↓", "Success ↑", "Coll. ↓", "Min dist (m) ↑"):
        t1.add_column(c, justify="left" if c in ("Scenario", "Method") else "right", no_wrap=True)
    t2 = Table(title=f"Trajectories vs the expert (CoNVOI Table II style), mean of {n_seeds} seed(s)")
    for c in ("Scenario", "Method", "Fréchet ↓", "Norm. Traj. Length ≈1", "Mean Velocity ↑", "DWA fallbacks", "ms/step"):
        t2.add_column(c, justify="left" if c in ("Scenario", "Method") else "right", no_wrap=True)
    t3 = Table(title="CoNVOI reference paths vs the expert's (CoNVOI Table I style), rule-based VLM")
    for c in ("Scenario", "Method", "Ref. Path Error ↓", "Cosine Sim. ↑", "Unacceptable ↓", "Inference (s) ↓",
              "Queries", "Failed", "Extrap."):
        t3.add_column(c, justify="left" if c in ("Scenario", "Method") else "right", no_wrap=True)
    last = None
    for d in summary:
        scen = d["scenario"] if d["scenario"] != last else ""
        if d["scenario"] != last and last is not None:
            t1.add_section()
            t2.add_section()
        last = d["scenario"]
        label = METHOD_LABELS.get(d["method"], d["method"])
        t1.add_row(scen, label, f(d["mse"], 4), f(d["hausdorff"], 4), f(d["psv"], 1), f(d["success"], 2),
                   f(d["collisions"], 1), f(d["min_distance"], 2))
        t2.add_row(scen, label, f(d["frechet"]), f(d["norm_length"]), f(d["mean_velocity"]), f(d["fallbacks"], 1),
                   f(d["plan_ms"], 1))
        if d["method"] == "convoi":
            t3.add_row(d["scenario"], "Rules VLM w. CoNVOI", f(d["ref_error"]), f(d["cosine"]), f(d["unacceptable"]),
                       f(d["latency_s"], 4), f(d["queries"], 1), f(d["failures"], 1), f(d["extrapolations"], 1))
    t1.caption = ("MSE: mean squared distance to the expert after arc-length resampling (m²); PSV: time with an "
                  "edge-to-edge gap < 0.25 m to a person; success: goal reached without collision")
    t2.caption = ("Fréchet: discrete, to the expert's trajectory; length normalised by the straight line from the start "
                  "to where the robot stopped (within 0.3 m of the goal when it succeeded)")
    t3.caption = ("ground truth: per marker row, the marker nearest to the expert's route; unacceptable: through an "
                  "obstacle, a person or a group (share in [0, 1], as the paper prints it)")
    return t1, t2, t3
