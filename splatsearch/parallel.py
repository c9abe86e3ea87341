"""Run independent jobs in parallel and yield their outcomes as they finish: one seam, two backends.

* ``local`` (the default, no extra dependency): worker processes on this machine, started with
  ``spawn`` (Warp and XLA hold threads, so they are never forked). ``workers=1`` runs the jobs in
  the calling process, as a plain loop.
* ``ray`` (``pip install 'splatsearch[ray]'``): long-lived Ray actors, one per worker, on a local
  Ray (started here when no ``address`` is given) or a running cluster (``address="auto"`` or
  ``"ray://host:10001"``). Each actor asks for ``cpus_per_job`` CPUs and ``gpus_per_job`` GPUs.

Both backends keep one job per worker at a time, so the count of running jobs is exact and a
worker that dies takes exactly one job with it. That job is run again on a fresh worker (a
worker that dies is replaced) up to ``max_attempts`` times in all, then reported as an error;
the other jobs go on. A job that raises is not retried (the episodes are deterministic: it would
raise again); its traceback is its :attr:`Outcome.error`. ``warmup(*warmup_args)`` runs once when a
worker starts, before its first job, so per-process state (thread counts, the JAX compile cache,
imported modules and loaded Warp kernels) is paid once per worker rather than once per job.
Interrupting the iteration (Ctrl-C, or leaving the ``for`` loop early) stops every worker and
drops the jobs not yet finished; every outcome already yielded stays with the caller.

A job is a module-level function plus picklable arguments (:class:`Job`): Ray ships them to
other machines, so closures and lambdas are refused up front with a clear error.

Typical use, with results saved by the caller after every outcome::

    with make_executor("ray", workers=8, address="auto", warmup=warm_worker, warmup_args=(1,)) as ex:
        for out in ex.run(jobs):
            results[out.key] = out.value if out.ok else {"error": out.error}
            save(results)
"""

from __future__ import annotations

import argparse
import os
import socket
import time
import traceback
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

BACKENDS = ("local", "ray")


@dataclass(frozen=True)
class Job:
    """One independent piece of work: ``fn(*args)``. ``key`` names it in outcomes and on resume;
    ``fn`` must be a module-level function (it is pickled by name)."""

    key: str
    fn: Callable[..., Any]
    args: tuple = ()


@dataclass
class Outcome:
    """What became of a :class:`Job`: ``value`` (``fn``'s return value) when ``error`` is None,
    else ``error`` (a traceback, or why the worker was lost). ``attempts``: runs started
    (2 = retried once after its worker died); ``wall_s``: seconds of the last run, measured in
    the worker; ``worker``: ``host:pid`` of the worker that ran it last."""

    key: str
    value: Any = None
    error: str | None = None
    attempts: int = 1
    wall_s: float = 0.0
    worker: str = ""

    @property
    def ok(self) -> bool:
        return self.error is None


@dataclass
class Counts:
    """Jobs of one :meth:`Executor.run` so far: ``done`` (finished, ok or not), ``running``,
    ``failed`` (finished with an error), ``retried`` (runs started again after a worker died),
    ``workers`` (alive now) and ``total``."""

    total: int = 0
    done: int = 0
    running: int = 0
    failed: int = 0
    retried: int = 0
    workers: int = 0

    def line(self) -> str:
        """e.g. ``"done 4/10 · running 2 · failed 0"`` for a progress bar."""
        s = f"done {self.done}/{self.total} · running {self.running} · failed {self.failed}"
        return s + (f" · retried {self.retried}" if self.retried else "")


class WorkerStartError(RuntimeError):
    """A worker's warm-up raised: every job would fail the same way, so the run stops."""


def worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def _check_job(job: Job) -> None:
    fn = job.fn
    qual = getattr(fn, "__qualname__", "")
    if not callable(fn) or "<lambda>" in qual or "<locals>" in qual:
        raise TypeError(f"job {job.key!r}: fn must be a module-level function (it is pickled by name), got {fn!r}")


def _call(fn: Callable, args: tuple) -> tuple[bool, Any, float]:
    """Run a job in a worker: (ok, value or traceback text, seconds)."""
    t0 = time.perf_counter()
    try:
        return True, fn(*args), time.perf_counter() - t0
    except Exception:  # noqa: BLE001 - the job's error goes back to the driver as text
        return False, traceback.format_exc(), time.perf_counter() - t0


class Executor:
    """Base of the backends: :meth:`run` yields an :class:`Outcome` per job as jobs finish (not
    in submission order). ``on_update(counts)`` is called whenever a job starts or ends."""

    backend = ""

    def __init__(self, workers: int, *, warmup: Callable[..., Any] | None = None, warmup_args: tuple = (),
                 max_attempts: int = 2):
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        if max_attempts < 1:
            raise ValueError(f"max_attempts must be >= 1, got {max_attempts}")
        if warmup is not None:
            _check_job(Job("warmup", warmup))
        self.workers = workers
        self.warmup = warmup
        self.warmup_args = tuple(warmup_args)
        self.max_attempts = max_attempts
        self.counts = Counts()

    def run(self, jobs: Iterable[Job], on_update: Callable[[Counts], None] | None = None) -> Iterator[Outcome]:
        jobs = list(jobs)
        keys = [j.key for j in jobs]
        if len(set(keys)) != len(keys):
            raise ValueError("job keys must be unique")
        for j in jobs:
            _check_job(j)
        self.counts = Counts(total=len(jobs))
        notify = on_update or (lambda c: None)
        finished = False
        try:
            yield from self._run(jobs, notify)
            finished = True
        finally:
            if not finished:  # Ctrl-C, an error, or the caller stopped iterating: drop the rest
                self._cancel()

    def _finish(self, out: Outcome, notify) -> Outcome:
        c = self.counts
        c.done += 1
        c.failed += not out.ok
        notify(c)
        return out

    def _lost(self, key: str, attempts: int, why: str) -> Outcome | None:
        """A worker died running job ``key`` on attempt ``attempts``: None to run it again,
        else its error outcome."""
        if attempts < self.max_attempts:
            self.counts.retried += 1
            return None
        return Outcome(key, error=f"worker lost on each of {attempts} attempts (last: {why})", attempts=attempts)

    def _run(self, jobs: list[Job], notify) -> Iterator[Outcome]:
        raise NotImplementedError

    def _cancel(self) -> None:
        raise NotImplementedError

    def close(self) -> None:
        """Stop the workers (and a Ray this executor started)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# -- local processes ----------------------------------------------------------------------------

def _local_worker(conn, warmup, warmup_args) -> None:
    """Body of a local worker process: warm up, then run jobs sent on ``conn`` until None."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the driver's to handle
    try:
        if warmup is not None:
            warmup(*warmup_args)
        conn.send(("ready", None))
    except Exception:  # noqa: BLE001
        conn.send(("ready", traceback.format_exc()))
        return
    while True:
        try:
            msg = conn.recv()
        except EOFError:
            return
        if msg is None:
            return
        seq, fn, args = msg
        ok, value, dt = _call(fn, args)
        try:
            conn.send(("done", seq, ok, value, dt))
        except Exception as e:  # noqa: BLE001 - e.g. a result that cannot be pickled
            conn.send(("done", seq, False, f"could not send the result back: {e!r}", dt))


class _Proc:
    def __init__(self, ctx, warmup, warmup_args):
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_local_worker, args=(child, warmup, warmup_args), daemon=True)
        self.proc.start()
        child.close()
        self.name = f"{socket.gethostname()}:{self.proc.pid}"
        self.seq: int | None = None  # the job it runs

    def stop(self, kill: bool = False) -> None:
        if self.proc.is_alive():
            if kill:
                self.proc.kill()
            else:
                try:
                    self.conn.send(None)
                except (OSError, ValueError):
                    self.proc.kill()
        self.proc.join(timeout=5 if not kill else 1)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join()
        self.conn.close()


class LocalExecutor(Executor):
    """Worker processes on this machine (``spawn``); ``workers=1`` runs jobs in this process
    (no warm-up is run there: the caller's process is already set up)."""

    backend = "local"

    def __init__(self, workers: int = 1, **kw):
        super().__init__(workers, **kw)
        self._procs: list[_Proc] = []

    def _run(self, jobs, notify):
        if self.workers == 1:
            yield from self._run_inline(jobs, notify)
            return
        import multiprocessing as mp
        from multiprocessing.connection import wait

        ctx = mp.get_context("spawn")
        todo = deque(range(len(jobs)))
        attempts = [0] * len(jobs)
        c = self.counts
        while todo or any(p.seq is not None for p in self._procs):
            while todo and len(self._procs) < min(self.workers, len(todo) + c.running):
                self._procs.append(_Proc(ctx, self.warmup, self.warmup_args))
            for p in self._procs:
                if p.seq is None and todo:
                    i = todo.popleft()
                    p.seq = i
                    attempts[i] += 1
                    p.conn.send((i, jobs[i].fn, jobs[i].args))
                    c.running += 1
            c.workers = len(self._procs)
            notify(c)
            by_obj = {}
            for p in self._procs:
                by_obj[p.conn] = p
                by_obj[p.proc.sentinel] = p
            seen = set()
            for obj in wait(list(by_obj)):
                p = by_obj[obj]
                if id(p) in seen:
                    continue
                seen.add(id(p))
                msg, gone = None, False
                try:
                    if p.conn.poll():
                        msg = p.conn.recv()
                except (EOFError, OSError):
                    gone = True
                if msg is not None and msg[0] == "ready":
                    if msg[1] is not None:
                        raise WorkerStartError(f"a worker's warm-up failed:\n{msg[1]}")
                    continue
                if msg is not None:
                    _, seq, ok, value, dt = msg
                    p.seq = None
                    c.running -= 1
                    yield self._finish(Outcome(jobs[seq].key, value if ok else None, None if ok else value,
                                               attempts[seq], dt, p.name), notify)
                    continue
                if not gone and p.proc.is_alive():
                    continue
                # the process is gone: its job (if any) is lost with it
                p.proc.join(timeout=1)
                why = f"worker {p.name} exited with code {p.proc.exitcode}"
                self._procs.remove(p)
                p.stop(kill=True)
                if p.seq is not None:
                    c.running -= 1
                    out = self._lost(jobs[p.seq].key, attempts[p.seq], why)
                    if out is None:
                        todo.appendleft(p.seq)
                    else:
                        yield self._finish(out, notify)

    def _run_inline(self, jobs, notify):
        c = self.counts
        c.workers = 1
        for j in jobs:
            c.running = 1
            notify(c)
            ok, value, dt = _call(j.fn, j.args)
            c.running = 0
            yield self._finish(Outcome(j.key, value if ok else None, None if ok else value, 1, dt, worker_name()),
                               notify)

    def _cancel(self) -> None:
        for p in self._procs:
            p.stop(kill=True)
        self._procs = []
        self.counts.running = 0
        self.counts.workers = 0

    def close(self) -> None:
        for p in self._procs:
            p.stop()
        self._procs = []


# -- Ray ----------------------------------------------------------------------------------------

class _RayWorker:
    """A long-lived Ray actor: warms up once, then runs one job per :meth:`run` call."""

    def __init__(self, warmup, warmup_args):
        self.error = None
        try:
            if warmup is not None:
                warmup(*warmup_args)
        except Exception:  # noqa: BLE001 - reported by ready(), so the driver can stop the run
            self.error = traceback.format_exc()

    def ready(self) -> tuple[str, str | None]:
        return worker_name(), self.error

    def run(self, fn, args) -> tuple[bool, Any, float, str]:
        ok, value, dt = _call(fn, args)
        return ok, value, dt, worker_name()


def import_ray():
    """The ``ray`` module, or an ImportError that says how to install it."""
    try:
        import ray
    except ImportError as e:
        raise ImportError("the ray backend needs Ray: pip install 'splatsearch[ray]'") from e
    return ray


class RayExecutor(Executor):
    """Ray actors, one per worker. ``address``: None starts a local Ray (stopped again by
    :meth:`close`); ``"auto"`` joins the cluster this machine belongs to; ``"ray://host:10001"``
    a remote one. ``workers``: None takes as many as the cluster's CPUs allow
    (``cpus_per_job`` each). A Ray already initialised by the caller is used as it is."""

    backend = "ray"

    def __init__(self, workers: int | None = None, *, address: str | None = None, cpus_per_job: float = 1,
                 gpus_per_job: float = 0, **kw):
        ray = import_ray()
        if cpus_per_job <= 0 or gpus_per_job < 0:
            raise ValueError(f"need cpus_per_job > 0 and gpus_per_job >= 0, got {cpus_per_job}, {gpus_per_job}")
        self._owns_ray = False
        if not ray.is_initialized():
            init_kw: dict[str, Any] = {"address": address, "logging_level": "warning"}
            if address is None:
                # Ray runs its workers at nice 15 to keep its own daemons responsive; here the
                # workers are the whole workload, and at nice 15 on a machine shared with other
                # programs they get a fraction of the CPU the process pool's workers get
                init_kw.update(include_dashboard=False, _system_config={"worker_niceness": 0})
            ray.init(**init_kw)
            self._owns_ray = True
        if workers is None:
            cpus = ray.cluster_resources().get("CPU", 1)
            workers = max(1, int(cpus // cpus_per_job))
        super().__init__(workers, **kw)
        self._ray = ray
        self.cpus_per_job, self.gpus_per_job = cpus_per_job, gpus_per_job
        # no restarts by Ray: a lost actor's job is retried here, on a new actor, and counted
        self._actor_cls = ray.remote(_RayWorker).options(num_cpus=cpus_per_job, num_gpus=gpus_per_job,
                                                          max_restarts=0, max_task_retries=0)
        self._actors: list = []

    def _new_actor(self):
        return self._actor_cls.remote(self.warmup, self.warmup_args)

    def _run(self, jobs, notify):
        ray = self._ray
        todo = deque(range(len(jobs)))
        attempts = [0] * len(jobs)
        idle = deque(self._actors)
        running: dict = {}  # ref -> (actor, job index)
        ready: dict = {}  # ready() ref -> actor
        c = self.counts
        while todo or running:
            while todo and len(self._actors) < min(self.workers, len(todo) + len(running)):
                a = self._new_actor()
                self._actors.append(a)
                ready[a.ready.remote()] = a
                idle.append(a)
            while todo and idle:
                a = idle.popleft()
                i = todo.popleft()
                attempts[i] += 1
                running[a.run.remote(jobs[i].fn, jobs[i].args)] = (a, i)
            c.running = len(running)
            c.workers = len(self._actors)
            notify(c)
            done, _ = ray.wait(list(running) + list(ready), num_returns=1, timeout=1.0)
            for ref in done:
                if ref in ready:
                    ready.pop(ref)
                    try:
                        _, err = ray.get(ref)
                    except ray.exceptions.RayError:
                        continue  # the actor died: its job's ref reports that
                    if err is not None:
                        raise WorkerStartError(f"a worker's warm-up failed:\n{err}")
                    continue
                a, i = running.pop(ref)
                try:
                    ok, value, dt, name = ray.get(ref)
                except ray.exceptions.RayTaskError as e:  # e.g. the result could not be serialised
                    idle.append(a)
                    yield self._finish(Outcome(jobs[i].key, error=str(e), attempts=attempts[i]), notify)
                    continue
                except ray.exceptions.RayError as e:  # the actor (its process or node) is gone
                    self._drop(a)
                    out = self._lost(jobs[i].key, attempts[i], f"{type(e).__name__}: {str(e).splitlines()[0]}")
                    if out is None:
                        todo.appendleft(i)
                    else:
                        yield self._finish(out, notify)
                    continue
                idle.append(a)
                yield self._finish(Outcome(jobs[i].key, value if ok else None, None if ok else value,
                                           attempts[i], dt, name), notify)
        c.running = 0

    def _drop(self, actor) -> None:
        try:
            self._ray.kill(actor, no_restart=True)
        except Exception:  # noqa: BLE001 - already dead
            pass
        if actor in self._actors:
            self._actors.remove(actor)

    def _cancel(self) -> None:
        for a in list(self._actors):
            self._drop(a)
        self.counts.running = 0
        self.counts.workers = 0

    def close(self) -> None:
        self._cancel()
        if self._owns_ray and self._ray.is_initialized():
            self._ray.shutdown()
            self._owns_ray = False


# -- construction and CLI flags -----------------------------------------------------------------

def make_executor(backend: str = "local", workers: int | None = None, *, address: str | None = None,
                  cpus_per_job: float = 1, gpus_per_job: float = 0, warmup: Callable[..., Any] | None = None,
                  warmup_args: tuple = (), max_attempts: int = 2) -> Executor:
    """An executor for ``backend`` (``"local"`` or ``"ray"``). ``workers`` None: 1 locally, as
    many as the cluster's CPUs allow on Ray. ``address``, ``cpus_per_job`` and ``gpus_per_job``
    are Ray's (see :class:`RayExecutor`); ``address`` with the local backend is an error."""
    kw = {"warmup": warmup, "warmup_args": warmup_args, "max_attempts": max_attempts}
    if backend == "local":
        if address is not None:
            raise ValueError("--address is for --backend ray")
        if gpus_per_job:
            raise ValueError("--gpus-per-job is for --backend ray")
        return LocalExecutor(1 if workers is None else workers, **kw)
    if backend == "ray":
        return RayExecutor(workers, address=address, cpus_per_job=cpus_per_job, gpus_per_job=gpus_per_job, **kw)
    raise ValueError(f"unknown backend {backend!r}; expected one of {BACKENDS}")


def add_executor_args(p: argparse.ArgumentParser, default_workers: int | None = 1) -> None:
    """``--backend``, ``--address``, ``--workers`` and ``--gpus-per-job`` for a command that runs
    jobs through :func:`executor_from_args`."""
    p.add_argument("--backend", choices=BACKENDS, default="local",
                   help="where jobs run: local worker processes (default) or a Ray cluster "
                        "(pip install 'splatsearch[ray]')")
    p.add_argument("--address", default=None,
                   help="Ray cluster to join: 'auto' (the cluster this machine is part of, after `ray start`) or "
                        "ray://HOST:10001; default: start a local Ray (ray backend only)")
    p.add_argument("--workers", type=int, default=default_workers,
                   help="parallel workers (default: 1 with --backend local, one per cluster CPU with ray)")
    p.add_argument("--gpus-per-job", type=float, default=0,
                   help="GPUs each Ray worker asks for, e.g. 0.25 (default 0; ray backend only)")


def executor_from_args(args: argparse.Namespace, **kw) -> Executor:
    """:func:`make_executor` from the flags of :func:`add_executor_args`."""
    workers = args.workers
    if workers is not None and workers < 1:
        raise ValueError(f"--workers must be >= 1, got {workers}")
    return make_executor(args.backend, workers, address=args.address, gpus_per_job=args.gpus_per_job, **kw)


# -- worker warm-up -----------------------------------------------------------------------------

def limit_threads(threads: int) -> None:
    """Give this worker process ``threads`` cores: Warp's CPU bands (the rasterizer's default
    thread count, :func:`splatsearch.kernels.config.set_default_threads`) and XLA's pool would
    otherwise each take every core in every worker and fight over them. XLA reads its pool size
    only from ``XLA_FLAGS``, so that is set in this (worker) process's environment. Call before
    the first JAX computation."""
    from splatsearch.kernels.config import set_default_threads

    set_default_threads(threads)
    flags = os.environ.get("XLA_FLAGS", "")
    if "intra_op_parallelism_threads" not in flags:
        os.environ["XLA_FLAGS"] = (flags + f" --xla_cpu_multi_thread_eigen={str(threads > 1).lower()}"
                                   f" intra_op_parallelism_threads={threads}").strip()


def warm_worker(threads: int, modules: tuple[str, ...] = ()) -> None:
    """Standard warm-up of a worker process: :func:`limit_threads`, the persistent JAX compile
    cache on, ``modules`` imported, Warp initialised and every Warp kernel module they define
    loaded (from Warp's on-disk kernel cache, compiled on a cold cache). Programs JAX compiles
    later stay in the worker's memory for all of its jobs."""
    import importlib

    limit_threads(threads)
    from splatsearch.compile_cache import enable_compile_cache

    enable_compile_cache()
    import warp as wp

    wp.config.quiet = True
    wp.init()
    for m in modules:
        importlib.import_module(m)
    if modules:
        wp.force_load(device="cpu")


def noop(x: Any = None) -> Any:
    """A job that does nothing: returns its argument (scheduling-overhead measurements, tests)."""
    return x
