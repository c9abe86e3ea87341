"""SR / SPL evaluation of SplatSearch and its ablations (thesis Tables III and IV).

Episodes come from procedural houses whose seeds derive from the evaluation seed
(``house_seeds``), so evaluation houses can be kept apart from those used for tuning. Episodes
run as independent jobs through :mod:`splatsearch.parallel` (in this process, local worker
processes, or a Ray cluster); results are written as JSON and as a markdown table.
"""

from __future__ import annotations

import json
import os
import time

import numpy as np

from splatsearch.agent import VARIANTS, AgentConfig
from splatsearch.cli_config import apply_overrides
from splatsearch.io import atomic_write_bytes
from splatsearch.parallel import Counts, Executor, Job, Outcome, make_executor, warm_worker

#: evaluation houses start here, away from the seeds 0..99 used while developing
EVAL_SEED_BASE = 1000


def house_seeds(seed: int, n_houses: int) -> list[int]:
    """Seeds of the evaluation houses for evaluation seed ``seed``."""
    return [EVAL_SEED_BASE + 100 * seed + i for i in range(n_houses)]


def make_eval_episodes(split: str, n: int, seed: int = 0, per_house: int = 5, *,
                       identical_furniture: bool = False) -> list:
    """``n`` episodes of ``split``, ``per_house`` per house, in houses :func:`house_seeds`
    (built with ``identical_furniture``, see :func:`splatsearch.sim.make_house`)."""
    from splatsearch import sim

    if n < 1:
        raise ValueError(f"the number of episodes must be >= 1, got {n}")
    if per_house < 1:
        raise ValueError(f"episodes per house must be >= 1, got {per_house}")
    eps = []
    for hs in house_seeds(seed, -(-n // per_house)):
        house = sim.make_house(hs, identical_furniture=identical_furniture)
        env = sim.HouseEnv(house)
        k = min(per_house, n - len(eps))
        for e in sim.make_episodes(house, k, split, seed=seed, env=env):
            e.episode_id = len(eps)
            eps.append(e)
    return eps


def _run_one(args):
    ep_json, variant, max_steps, overrides = args
    import warp as wp

    wp.config.quiet = True
    from splatsearch.episode import run_episode
    from splatsearch.sim.episodes import Episode

    ep = Episode.from_json(ep_json)
    t0 = time.perf_counter()
    try:
        r = run_episode(ep, apply_overrides(AgentConfig(variant=variant), overrides), max_steps=max_steps)
    except Exception as e:  # noqa: BLE001 - one broken episode must not end the whole evaluation
        import traceback

        return {"episode_id": ep.episode_id, "house_seed": ep.house_seed, "variant": variant, "success": False,
                "spl": 0.0, "steps": 0, "wall_time": time.perf_counter() - t0, "status": "error",
                "error": "".join(traceback.format_exception_only(type(e), e)).strip()}
    d = r.to_json()
    d.pop("trajectory")
    d["identical_furniture"] = bool(ep.identical_furniture)
    if overrides:
        d["agent_overrides"] = overrides
    return d


def summarise(results: list[dict]) -> dict[str, dict]:
    """Per variant: n, SR, SPL, mean steps, median and mean wall time (s), errors.

    An episode that raised (``"error"`` in its result) counts as a failure in SR and SPL, and is
    left out of the step and wall-time statistics.
    """
    out = {}
    for v in dict.fromkeys(r["variant"] for r in results):
        rs = [r for r in results if r["variant"] == v]
        ran = [r for r in rs if "error" not in r]
        steps = np.array([r["steps"] for r in ran], float)
        wall = np.array([r["wall_time"] for r in ran], float)
        out[v] = {"n": len(rs), "SR": float(np.mean([r["success"] for r in rs])),
                  "SPL": float(np.mean([r["spl"] for r in rs])),
                  "steps": float(steps.mean()) if len(ran) else float("nan"),
                  "median_wall_s": float(np.median(wall)) if len(ran) else float("nan"),
                  "mean_wall_s": float(wall.mean()) if len(ran) else float("nan"),
                  "errors": len(rs) - len(ran)}
    return out


def eval_title(split: str, n: int, seed: int, identical_furniture: bool = False, agent_overrides: dict | None = None) -> str:
    """The heading of an evaluation's table. It always names the detector and matcher: with the
    default ``sim`` detector every number rests on the simulator's ground-truth masks (an oracle)."""
    over = dict(agent_overrides or {})
    detector, matcher = over.pop("detector", "sim"), over.pop("matcher", "sift")
    extra = ", identical furniture" if identical_furniture else ""
    if over:
        extra += ", agent " + ", ".join(f"{k}={v}" for k, v in sorted(over.items()))
    oracle = " (simulator ground-truth masks, an oracle)" if detector == "sim" else ""
    return f"{split}, {n} episodes, seed {seed}{extra}; detector {detector}{oracle}, matcher {matcher}"


def markdown_table(summary: dict[str, dict], title: str) -> str:
    """The summary as a markdown table."""
    lines = [f"### {title}", "", "| method | episodes | SR | SPL | mean steps | median wall s | errors |",
             "|---|---|---|---|---|---|---|"]
    for v, s in summary.items():
        lines.append(f"| {v} | {s['n']} | {s['SR']:.3f} | {s['SPL']:.3f} | {s['steps']:.0f} | "
                     f"{s['median_wall_s']:.1f} | {s.get('errors', 0)} |")
    return "\n".join(lines) + "\n"


#: modules a worker imports (and whose Warp kernels it loads) once, before its first episode
WORKER_MODULES = ("splatsearch.episode",)


def _worker_threads(executor: Executor) -> int:
    """Cores per worker: this machine's share per local worker, a Ray job's CPU request on Ray."""
    from splatsearch.kernels.parallel import cpu_threads

    if executor.backend == "ray":
        return max(1, int(executor.cpus_per_job))
    return max(1, cpu_threads() // executor.workers)


def _error_result(ep, variant: str, outcome: Outcome) -> dict:
    """The result of an episode whose job did not return (its worker was lost twice)."""
    return {"episode_id": ep.episode_id, "house_seed": ep.house_seed, "variant": variant, "success": False,
            "spl": 0.0, "steps": 0, "wall_time": outcome.wall_s, "status": "error", "error": outcome.error}


def evaluate(split: str = "val-hard", n: int = 50, seed: int = 0, variants=VARIANTS, workers: int | None = 1,
             out: str | None = None, max_steps: int | None = None, progress=None,
             resume: bool = False, identical_furniture: bool = False,
             agent_overrides: dict | None = None, *, backend: str = "local", address: str | None = None,
             gpus_per_job: float = 0, executor: Executor | None = None) -> tuple[list[dict], dict]:
    """Run every variant on the same ``n`` episodes. Returns (per-episode results, summary).

    Each (episode, variant) is one job run by ``executor``, or by one made here from ``backend``
    (``"local"``: ``workers`` processes on this machine, 1 = in this process; ``"ray"``: Ray
    actors on the cluster at ``address``, None = a local Ray; ``workers`` None = one per cluster
    CPU; ``gpus_per_job``: GPUs each Ray worker asks for). See :mod:`splatsearch.parallel`. Each
    worker warms up once (threads, the JAX compile cache, Warp kernels), not once per episode: the
    executor's warm-up is set to :func:`~splatsearch.parallel.warm_worker` here.
    The per-episode outcomes do not depend on the backend; ``results`` come back sorted by
    episode, then variant.

    Results are saved after every finished episode to ``out/results.json`` (atomically, so a
    crash, a lost worker or Ctrl-C keeps them) and the summary to ``out/summary.json`` and
    ``out/summary.md``. An episode whose worker dies is run again once, then recorded with
    ``"status": "error"``. ``resume`` keeps the results already in ``out/results.json`` (episode
    id, house and variant must match this run's episodes; errors are run again) and runs only the
    missing ones. ``identical_furniture`` builds the houses with one model per furniture class, so
    that only their surroundings tell same-class instances apart (see
    :func:`splatsearch.sim.make_house`). ``agent_overrides``: :class:`AgentConfig` fields set for
    every variant (e.g. ``{"colour_cue": False}``: identify by feature matches alone, as the
    thesis does, since colours cannot tell identical furniture apart); a resume keeps only results
    run with the same overrides. ``progress(result, counts)`` is called when an episode starts
    (``result`` None) or ends, with the :class:`~splatsearch.parallel.Counts` of this run (done,
    running, failed; ``total`` includes resumed episodes).
    """
    from splatsearch.agent.variants import VARIANT_ALIASES

    bad = [v for v in variants if v not in VARIANTS and v not in VARIANT_ALIASES]
    if bad:
        raise ValueError(f"unknown variant(s) {bad}; expected some of {VARIANTS} (aliases: {VARIANT_ALIASES})")
    # an alias runs (and is recorded as) the variant it names, so results stay comparable
    variants = list(dict.fromkeys(VARIANT_ALIASES.get(v, v) for v in variants))
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    overrides = dict(agent_overrides or {})
    bad = sorted((set(overrides) - set(AgentConfig.__dataclass_fields__)) | ({"variant"} & set(overrides)))
    if bad:
        raise ValueError(f"agent_overrides: not settable AgentConfig fields: {bad}")
    apply_overrides(AgentConfig(), overrides)  # invalid values fail here, not in every worker
    if resume and not out:
        raise ValueError("resume needs out (the folder with results.json)")
    eps = make_eval_episodes(split, n, seed, identical_furniture=identical_furniture)
    # episode-major: an interrupted run still holds every variant on the same first episodes
    results: list[dict] = []
    if resume:
        path = os.path.join(out, "results.json")
        if os.path.exists(path):
            with open(path) as f:
                old = json.load(f)
            houses = {e.episode_id: e.house_seed for e in eps}
            results = [r for r in old if r.get("variant") in variants and houses.get(r.get("episode_id")) == r.get("house_seed")
                       and "error" not in r and bool(r.get("identical_furniture", False)) == identical_furniture
                       and r.get("agent_overrides", {}) == overrides]
    done = {(r["episode_id"], r["variant"]) for r in results}
    todo = {f"{e.episode_id}/{v}": (e, v) for e in eps for v in variants if (e.episode_id, v) not in done}
    jobs = [Job(k, _run_one, ((e.to_json(), v, max_steps, overrides),)) for k, (e, v) in todo.items()]
    t0 = time.perf_counter()
    order = {v: i for i, v in enumerate(variants)}

    def save():
        if out:
            os.makedirs(out, exist_ok=True)
            atomic_write_bytes(os.path.join(out, "results.json"), json.dumps(results, indent=1).encode())

    n_resumed = len(results)

    def shown(c: Counts) -> Counts:
        return Counts(c.total + n_resumed, c.done + n_resumed, c.running, c.failed, c.retried, c.workers)

    own = executor is None
    if own:
        executor = make_executor(backend, workers, address=address, gpus_per_job=gpus_per_job)
    try:
        executor.warmup, executor.warmup_args = warm_worker, (_worker_threads(executor), WORKER_MODULES)
        on_update = (lambda c: progress(None, shown(c))) if progress else None
        for o in executor.run(jobs, on_update):
            e, v = todo[o.key]
            results.append(o.value if o.ok else _error_result(e, v, o))
            save()
            if progress:
                progress(results[-1], shown(executor.counts))
    finally:
        if own:
            executor.close()
    results.sort(key=lambda r: (r["episode_id"], order.get(r["variant"], len(order))))
    save()
    summary = summarise(results)
    if out:
        meta = {"split": split, "episodes": n, "seed": seed, "identical_furniture": identical_furniture,
                "agent_overrides": overrides,
                "house_seeds": sorted({e.house_seed for e in eps}),
                "backend": executor.backend, "workers": executor.workers,
                "total_wall_s": time.perf_counter() - t0, "summary": summary}
        atomic_write_bytes(os.path.join(out, "summary.json"), json.dumps(meta, indent=1).encode())
        atomic_write_bytes(os.path.join(out, "summary.md"),
                           markdown_table(summary, eval_title(split, n, seed, identical_furniture, overrides)).encode())
    return results, summary
