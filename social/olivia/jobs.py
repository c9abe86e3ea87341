"""OLiVia-Nav's long loops as independent jobs for :mod:`splatsearch.parallel` (local processes or
a Ray cluster): the expert data, one job per (split, scenario, seed), and Table I, one job per
(scenario, seed).

Nothing is lost: every finished data job is written at once (atomically) to
``OUT/parts/``, every finished Table I job to ``OUT/table1_jobs.json``; a rerun with ``resume``
runs only what is missing. The outputs are the same as the sequential
:func:`~splatsearch.social.olivia.dataset.build_dataset` and
:func:`~splatsearch.social.olivia.train.table_one` give (same jobs, same order of concatenation
and averaging).
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable, Sequence

logger = logging.getLogger(__name__)

#: modules a worker imports (and whose Warp kernels it loads) once, before its first job
WORKER_MODULES = ("splatsearch.social.olivia.dataset", "splatsearch.social.olivia.train")


def _threads(executor) -> int:
    from splatsearch.kernels.parallel import cpu_threads

    if executor.backend == "ray":
        return max(1, int(executor.cpus_per_job))
    return max(1, cpu_threads() // executor.workers)


def _prepare(executor) -> None:
    from splatsearch.parallel import warm_worker

    executor.warmup, executor.warmup_args = warm_worker, (_threads(executor), WORKER_MODULES)


# -- expert data ---------------------------------------------------------------------------------

def data_job(scenario: str, seed: int, every: int, augment: int, vary_geometry: bool = False, headon: bool = False,
             perceived_berth: float = 0.0):
    """Samples of one expert episode (exactly :func:`build_dataset` on one scenario and seed;
    ``headon``: the doorway of that seed as a :func:`~splatsearch.social.olivia.dataset.headon_doorway`)."""
    from .dataset import build_dataset

    return build_dataset([scenario], [seed], every=every, augment=augment, vary_geometry=vary_geometry, headon=headon,
                         perceived_berth=perceived_berth)


def build_datasets(out_dir: str, scenarios: Sequence[str], splits: dict[str, Sequence[int]], *, every: int,
                   augment: int, executor, resume: bool = False, on_update: Callable | None = None,
                   vary_geometry: bool = False, door_seeds: Sequence[int] = (),
                   headon_door_seeds: Sequence[int] = (), perceived_berth: float = 0.0) -> dict:
    """``OUT/samples_{split}.npz`` for every split in ``splits`` (``{"train": seeds, "val": seeds}``),
    the files ``social train --out OUT`` reuses. Returns ``{split: number of samples}``.
    ``door_seeds`` / ``headon_door_seeds``: doorway scenes (sampled widths) and head-on doorway
    scenes (:func:`~splatsearch.social.olivia.dataset.headon_doorway`) appended to the "train"
    split after its scenarios, in the order ``social train`` builds them
    (``TrainConfig.door_seeds``, ``TrainConfig.headon_door_seeds``); ``perceived_berth``: the
    goal features' route (``TrainConfig.perceived_berth``).

    Raises RuntimeError naming the failed jobs when any failed (the finished parts stay in
    ``OUT/parts/`` for a ``resume``); ``on_update(counts)`` follows the jobs."""
    from splatsearch.parallel import Job

    from .dataset import Samples

    parts = os.path.join(out_dir, "parts")
    os.makedirs(parts, exist_ok=True)
    if (door_seeds or headon_door_seeds) and "train" not in splits:
        raise ValueError("door_seeds / headon_door_seeds go into the 'train' split, which splits lacks")
    order = []  # (split, scenario, seed, head-on), in social train's order of concatenation
    for split, seeds in splits.items():
        order += [(split, name, int(seed), False) for name in scenarios for seed in seeds]
        if split == "train":
            order += [(split, "doorway", int(seed), False) for seed in door_seeds]
            order += [(split, "doorway", int(seed), True) for seed in headon_door_seeds]

    def path(split, name, seed, headon):
        geo = "-geo" if vary_geometry or headon else ""  # never resume from parts of the other geometry
        kind = "-headon" if headon else ""
        pb = f"-pb{perceived_berth:g}" if perceived_berth > 0 else ""
        return os.path.join(parts, f"{split}-{name}{kind}-{seed}-every{every}-aug{augment}{geo}{pb}.npz")

    keys = {f"{split}/{name}{'-headon' if h else ''}/{seed}": (split, name, seed, h) for split, name, seed, h in order}
    if len(keys) != len(order):
        raise ValueError("a (split, scenario, seed) appears twice: door seeds must differ from the doorway's train seeds")
    jobs = [Job(key, data_job, (name, seed, every, augment, vary_geometry, h, perceived_berth))
            for key, (split, name, seed, h) in keys.items()
            if not (resume and os.path.exists(path(split, name, seed, h)))]
    _prepare(executor)
    failed = []
    for o in executor.run(jobs, on_update):
        if o.ok:
            o.value.save(path(*keys[o.key]))
        else:
            failed.append(f"{o.key}: {o.error.strip().splitlines()[-1]}")
    if failed:
        raise RuntimeError(f"{len(failed)} expert episode(s) failed (run again with --resume to retry them):\n"
                           + "\n".join(failed))
    sizes = {}
    for split in splits:
        s = Samples.concat([Samples.load(path(sp, n, k, h)) for sp, n, k, h in order if sp == split])
        s.save(os.path.join(out_dir, f"samples_{split}.npz"))
        sizes[split] = len(s)
    return sizes


# -- Table I -------------------------------------------------------------------------------------

_PLANNERS: dict = {}  # per worker process: (path, size, mtime) -> planner


def _planner(checkpoint: str, stamp: tuple):
    from .train import load_planner

    if not os.path.exists(checkpoint):
        raise FileNotFoundError(f"no checkpoint {checkpoint!r} on this worker: on a cluster, put it on storage "
                                "that every node mounts at the same path")
    key = (checkpoint, *stamp)
    if key not in _PLANNERS:
        _PLANNERS.clear()
        _PLANNERS[key] = load_planner(checkpoint)
    return _PLANNERS[key]


def table_one_job(checkpoint: str, stamp: tuple, scenario: str, seed: int, baselines: Sequence[str],
                  variants: Sequence[str], cache_dir: str | None = None, overrides: tuple = ()) -> dict:
    """Metrics of one (scenario, seed) for Table I: ``{method label: episode metrics}``, in the
    order :func:`~splatsearch.social.olivia.train.table_one` averages them. ``cache_dir``: a
    :class:`~splatsearch.social.olivia.baseline_cache.BaselineCache` directory for the reference
    and baseline episodes (shared by every worker on this machine). ``overrides``: ``(name, value)``
    pairs replacing fields of the checkpoint's :class:`~splatsearch.social.olivia.planner.OliviaConfig`."""
    from .baseline_cache import BaselineCache
    from .planner import VARIANT_LABELS, run_olivia_episode
    from .train import episode_metrics, run_baseline
    from ..convoi.runner import REFERENCE
    from ..convoi.scenarios import make_scenario

    planner = _planner(checkpoint, stamp)
    if overrides:
        import dataclasses

        from .planner import OliviaNav

        planner = OliviaNav(planner.params, planner.db, dataclasses.replace(planner.cfg, **dict(overrides)))
    cache = BaselineCache(cache_dir) if cache_dir else None
    scn = make_scenario(scenario, seed)
    ref = run_baseline(scn, REFERENCE, cache)
    out = {}
    for v in variants:
        out[VARIANT_LABELS[v]] = episode_metrics(run_olivia_episode(scn, planner.with_variant(v)), ref)
    names = {"dwa": "DWA", "convoi": "CoNVOI+DWA"}
    for b in baselines:
        out[names.get(b, b)] = episode_metrics(run_baseline(scn, b, cache), ref)
    return out


def table_one_parallel(checkpoint: str, scenarios: Sequence[str], seeds: Sequence[int], baselines: Sequence[str],
                       variants: Sequence[str], *, executor, out_dir: str, resume: bool = False,
                       on_update: Callable | None = None, log: Callable[[str], None] | None = None,
                       cache_dir: str | None = None, overrides: dict | None = None) -> list[dict]:
    """:func:`~splatsearch.social.olivia.train.table_one`'s rows, one job per (scenario, seed).
    Finished jobs go to ``out_dir/table1_jobs.json`` at once; ``resume`` reuses those run with the
    same checkpoint (path, size, mtime), baselines and variants. Raises RuntimeError naming the
    failed jobs (the finished ones stay saved). ``cache_dir``: reference and baseline episodes are
    read from / written to this :class:`~splatsearch.social.olivia.baseline_cache.BaselineCache`.
    ``overrides``: OliviaConfig fields replaced in every job (part of what a resume must match)."""
    log = log or logger.info  # a caller may pass console.log; the library logs by default
    from splatsearch.io import atomic_write_bytes
    from splatsearch.parallel import Job

    from .train import _mean, win_counts

    checkpoint = os.path.abspath(checkpoint)
    st = os.stat(checkpoint)
    stamp = (st.st_size, int(st.st_mtime_ns))
    ov = tuple(sorted((overrides or {}).items()))
    setup = {"checkpoint": checkpoint, "stamp": list(stamp), "baselines": list(baselines), "variants": list(variants)}
    if ov:
        setup["overrides"] = [list(x) for x in ov]
    store = os.path.join(out_dir, "table1_jobs.json")
    done: dict = {}
    if resume and os.path.exists(store):
        with open(store, encoding="utf-8") as f:
            saved = json.load(f)
        if saved.get("setup") == setup:
            done = saved["jobs"]
    jobs = [Job(f"{name}/{seed}", table_one_job, (checkpoint, stamp, name, int(seed), tuple(baselines), tuple(variants),
                                                       os.path.abspath(cache_dir) if cache_dir else None, ov))
            for name in scenarios for seed in seeds if f"{name}/{seed}" not in done]
    _prepare(executor)
    failed = []
    for o in executor.run(jobs, on_update):
        if o.ok:
            done[o.key] = o.value
            atomic_write_bytes(store, json.dumps({"setup": setup, "jobs": done}, indent=1).encode())
        else:
            failed.append(f"{o.key}: {o.error.strip().splitlines()[-1]}")
    if failed:
        raise RuntimeError(f"{len(failed)} Table I job(s) failed (run again with --resume to retry them):\n"
                           + "\n".join(failed))
    rows = []
    for name in scenarios:
        per: dict[str, list] = {}
        for seed in seeds:
            for method, m in done[f"{name}/{seed}"].items():
                per.setdefault(method, []).append(m)
        wins = win_counts(per)
        for method, ms in per.items():
            rows.append({"scenario": name, "method": method, "n": len(ms)} | _mean(ms)
                        | ({"wins": wins[method]} if method in wins else {}))
        log(f"Table I: {name} done")
    return rows
