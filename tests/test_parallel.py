"""The executor seam (splatsearch.parallel) on both backends, and evaluation through it.

The Ray tests start a local Ray with ``num_cpus=2`` (as CI does) and shut it down afterwards; they
are skipped only where Ray cannot be imported (``pip install 'splatsearch[ray]'``).
"""

import json
import os
import sys

import pytest
from parallel_jobs import boom, die_always, die_once, failing_warmup, square

from splatsearch.evaluation import evaluate
from splatsearch.parallel import (
    Job,
    LocalExecutor,
    WorkerStartError,
    add_executor_args,
    executor_from_args,
    make_executor,
    noop,
)

try:
    import ray
except ImportError:  # pragma: no cover - CI installs it with the test extra
    ray = None

needs_ray = pytest.mark.skipif(ray is None, reason="Ray is not installed (pip install 'splatsearch[ray]')")


@pytest.fixture(scope="module")
def ray_cluster():
    if ray is None:
        pytest.skip("Ray is not installed (pip install 'splatsearch[ray]')")
    from ray import cloudpickle

    # Ray workers do not have tests/ on their path: ship the test jobs by value
    cloudpickle.register_pickle_by_value(sys.modules["parallel_jobs"])
    ray.init(num_cpus=2, include_dashboard=False)
    yield
    ray.shutdown()


def _executor(backend, workers=2, **kw):
    return make_executor(backend, workers, **kw)


BACKENDS = ["local", pytest.param("ray", marks=needs_ray)]


@pytest.fixture(params=BACKENDS)
def backend(request):
    if request.param == "ray":
        request.getfixturevalue("ray_cluster")
    return request.param


def test_jobs_run_lost_workers_retried_and_errors_recorded(backend, tmp_path):
    """Results as jobs finish; a killed worker's job runs again (and succeeds), a job whose worker
    dies every time is an error after two attempts, a raising job is an error without a retry;
    the other jobs are unaffected and the workers are replaced."""
    jobs = [Job(f"sq{i}", square, (i,)) for i in range(5)]
    jobs += [Job("die_once", die_once, (str(tmp_path / "died"),)), Job("die_always", die_always),
             Job("boom", boom, (str(tmp_path / "boom"),))]
    seen = []
    with _executor(backend) as ex:
        outs = {o.key: o for o in ex.run(jobs, on_update=lambda c: seen.append((c.running, c.done)))}
        counts = ex.counts
        # the executor goes on working after losing workers
        again = [o.value for o in ex.run([Job("after", square, (7,))])]
    assert set(outs) == {j.key for j in jobs}
    assert all(outs[f"sq{i}"].ok and outs[f"sq{i}"].value == i * i and outs[f"sq{i}"].attempts == 1 for i in range(5))
    assert outs["die_once"].ok and outs["die_once"].value == "second try" and outs["die_once"].attempts == 2
    assert not outs["die_always"].ok and outs["die_always"].attempts == 2 and "worker lost" in outs["die_always"].error
    assert not outs["boom"].ok and "RuntimeError: boom" in outs["boom"].error and outs["boom"].attempts == 1
    assert (tmp_path / "boom").read_text() == "x"  # run once: a raising job is not retried
    assert (counts.total, counts.done, counts.failed, counts.retried, counts.running) == (8, 8, 2, 2, 0)
    assert max(r for r, _ in seen) <= 2 and seen[-1][1] == 8
    assert again == [49]


def test_stopping_early_cancels_the_rest(backend, tmp_path):
    """Leaving the loop (as Ctrl-C does) stops the workers; what was yielded is kept."""
    jobs = [Job(str(i), square, (i,)) for i in range(40)]
    with _executor(backend) as ex:
        got = []
        for o in ex.run(jobs):
            got.append(o)
            if len(got) == 3:
                break
        assert ex.counts.running == 0 and ex.counts.workers == 0
    assert len(got) == 3 and all(o.ok for o in got)


def test_failing_warmup_stops_the_run(backend):
    with _executor(backend, warmup=failing_warmup) as ex:
        with pytest.raises(WorkerStartError, match="no GPU here"):
            list(ex.run([Job("a", noop, (1,)), Job("b", noop, (2,))]))


def test_bad_jobs_and_arguments():
    with pytest.raises(TypeError, match="module-level"):
        list(LocalExecutor(1).run([Job("l", lambda: 1)]))
    with pytest.raises(ValueError, match="unique"):
        list(LocalExecutor(1).run([Job("a", noop), Job("a", noop)]))
    with pytest.raises(ValueError, match="workers"):
        make_executor("local", 0)
    with pytest.raises(ValueError, match="backend"):
        make_executor("slurm", 1)
    with pytest.raises(ValueError, match="--address"):
        make_executor("local", 2, address="auto")
    # in-process (workers=1): a raising job is an error outcome, the loop goes on
    outs = list(LocalExecutor(1).run([Job("e", boom, (os.devnull,)), Job("ok", square, (3,))]))
    assert [o.ok for o in outs] == [False, True] and outs[1].value == 9


def test_cli_flags():
    import argparse

    p = argparse.ArgumentParser()
    add_executor_args(p, default_workers=None)
    a = p.parse_args([])
    assert (a.backend, a.address, a.workers, a.gpus_per_job) == ("local", None, None, 0)
    ex = executor_from_args(a)
    assert ex.backend == "local" and ex.workers == 1
    with pytest.raises(ValueError, match="--workers"):
        executor_from_args(p.parse_args(["--workers", "0"]))
    with pytest.raises(SystemExit):
        p.parse_args(["--backend", "dask"])


# -- evaluation ---------------------------------------------------------------------------------

OUTCOME_KEYS = ("episode_id", "house_seed", "variant", "success", "spl", "steps", "path_length", "d_star",
                "final_distance", "status", "nvsm_runs", "n_objects")


def _outcomes(results):
    return [{k: r[k] for k in OUTCOME_KEYS} for r in results]


class _StopAfter:
    """A progress callback that interrupts the evaluation (as Ctrl-C) after ``n`` finished episodes."""

    def __init__(self, n):
        self.n = n

    def __call__(self, result, counts):
        if result is not None and counts.done >= self.n:
            raise KeyboardInterrupt


def test_evaluate_interrupt_and_resume_in_process(tmp_path):
    """Ctrl-C after the first episode keeps it in results.json; --resume runs only the rest."""
    kw = dict(split="val", n=2, seed=0, variants=("nearest_frontier",), out=str(tmp_path), max_steps=2)
    with pytest.raises(KeyboardInterrupt):
        evaluate(**kw, progress=_StopAfter(1))
    kept = json.loads((tmp_path / "results.json").read_text())
    assert len(kept) == 1
    calls = []
    results, summary = evaluate(**kw, resume=True, progress=lambda r, c: calls.append(r))
    assert results[kept[0]["episode_id"]] == kept[0]  # the finished episode is kept as it was
    assert sorted(r["episode_id"] for r in results) == [0, 1] and summary["nearest_frontier"]["n"] == 2
    assert sum(r is not None for r in calls) == 1  # only the missing episode ran
    assert json.loads((tmp_path / "results.json").read_text()) == results


@needs_ray
@pytest.mark.slow  # starts local workers and a Ray cluster twice (about 25 s on 2 cores); the executor tests above cover Ray by default
def test_ray_and_local_same_outcomes_and_resume(ray_cluster, tmp_path):
    """Two short episodes give the same per-episode outcomes on both backends (2 workers each);
    a Ray run interrupted after its first episode and resumed on Ray loses nothing."""
    kw = dict(split="val", n=2, seed=0, variants=("nearest_frontier",), max_steps=3, workers=2)
    local, _ = evaluate(**kw, backend="local", out=str(tmp_path / "local"))
    with pytest.raises(KeyboardInterrupt):
        evaluate(**kw, backend="ray", out=str(tmp_path / "ray"), progress=_StopAfter(1))
    kept = json.loads((tmp_path / "ray" / "results.json").read_text())
    assert len(kept) == 1
    on_ray, summary = evaluate(**kw, backend="ray", out=str(tmp_path / "ray"), resume=True)
    assert kept[0] in on_ray and summary["nearest_frontier"]["n"] == 2
    assert _outcomes(on_ray) == _outcomes(local)
    meta = json.loads((tmp_path / "ray" / "summary.json").read_text())
    assert meta["backend"] == "ray" and meta["workers"] == 2


# -- OLiVia-Nav ---------------------------------------------------------------------------------

def test_social_data_jobs_match_build_dataset_and_resume(tmp_path):
    """`social data` through the executor writes what build_dataset gives; a resume reuses the
    finished episodes (OUT/parts/) and runs nothing again."""
    import numpy as np

    from splatsearch.social.olivia.dataset import Samples, build_dataset
    from splatsearch.social.olivia.jobs import build_datasets

    kw = dict(every=12, augment=0)
    sizes = build_datasets(str(tmp_path), ("hallway",), {"train": (0,), "val": (50,)}, executor=LocalExecutor(1), **kw)
    got = Samples.load(str(tmp_path / "samples_train.npz"))
    want = build_dataset(("hallway",), (0,), **kw)
    assert sizes["train"] == len(want) > 0 and sizes["val"] > 0
    for k in ("image", "points", "goal", "future", "action", "seed", "t"):
        np.testing.assert_array_equal(getattr(got, k), getattr(want, k))
    assert got.long == want.long
    os.remove(tmp_path / "samples_train.npz")
    ex = LocalExecutor(1)
    again = build_datasets(str(tmp_path), ("hallway",), {"train": (0,), "val": (50,)}, executor=ex, resume=True, **kw)
    assert again == sizes and ex.counts.total == 0
    np.testing.assert_array_equal(Samples.load(str(tmp_path / "samples_train.npz")).image, want.image)


def test_social_cli_has_executor_flags():
    import argparse

    from splatsearch.social.olivia.cli import cmd_data, cmd_eval, register_olivia

    parser = argparse.ArgumentParser()
    register_olivia(parser.add_subparsers(dest="cmd"))
    a = parser.parse_args(["data", "--train-seeds", "0-3", "--backend", "ray", "--address", "auto", "--resume"])
    assert a.func is cmd_data and a.train_seeds == (0, 1, 2, 3) and (a.backend, a.address, a.resume) == ("ray", "auto", True)
    b = parser.parse_args(["eval", "--workers", "2", "--resume"])
    assert b.func is cmd_eval and (b.backend, b.workers, b.resume) == ("local", 2, True)


@pytest.mark.slow  # OLiVia-Nav's closed loop compiles for about a minute on 2 cores
def test_table_one_jobs_match_table_one(tmp_path):
    import jax

    from splatsearch.social.olivia import train as ot
    from splatsearch.social.olivia import sc_clip, tpn, tsm
    from splatsearch.social.olivia.llu import build_text_db
    from splatsearch.social.olivia.planner import OliviaConfig, OliviaNav
    from splatsearch.social.olivia.jobs import table_one_parallel

    cfg = OliviaConfig()
    k = jax.random.split(jax.random.PRNGKey(0), 3)
    params = {"clip": sc_clip.init_sc_clip(k[0], cfg.clip), "tpn": tpn.init_tpn(k[1], cfg.tpn),
              "tsm": tsm.init_tsm(k[2], cfg.tsm)}
    db = build_text_db(params["clip"], ["the space is open you should continue straight",
                                        "a wall is ahead you should turn left"], cfg.clip)
    path = str(tmp_path / "olivia.npz")
    ot.save_checkpoint(path, params, db=db, meta=ot.config_to_meta(cfg))
    # OLiVia-Nav runs in float32, as in the CLI (conftest turns float64 on for the references)
    jax.config.update("jax_enable_x64", False)
    try:
        want = ot.table_one(OliviaNav(params, db, cfg), ("hallway",), (1000,), ("dwa",), ("olivia",),
                            log=lambda s: None)
        got = table_one_parallel(path, ("hallway",), (1000,), ("dwa",), ("olivia",), executor=LocalExecutor(1),
                                 out_dir=str(tmp_path), log=lambda s: None)
    finally:
        jax.config.update("jax_enable_x64", True)
    def outcome(rows):  # plan_ms is a timing
        return [{k: v for k, v in r.items() if k != "plan_ms"} for r in rows]

    assert outcome(got) == outcome(want) and all(r["plan_ms"] > 0 for r in got)
    saved = json.loads((tmp_path / "table1_jobs.json").read_text())
    assert list(saved["jobs"]) == ["hallway/1000"]
