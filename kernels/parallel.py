"""CPU parallelism for Warp launches.

A Warp launch on the CPU runs on one thread. Warp releases the GIL inside a launch, so splitting
a launch into bands run from several Python threads uses every core. Bands go round-robin to
the workers, which keeps every worker's work, and hence any floating-point sums it owns, in a
fixed order: results are bitwise reproducible.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import warp as wp

from .config import default_threads, resolve_threads


def cpu_threads() -> int:
    """Default worker threads for CPU launches (see :mod:`splatsearch.kernels.config`)."""
    return default_threads()


def n_threads_for(device, threads: int | None = None) -> int:
    """Worker threads for a launch on ``device``: ``threads`` or the default on the CPU, 1 on CUDA."""
    return resolve_threads(threads, device)


# Module-level pool of band workers, created on first use (per process: a forked child makes its
# own, since the parent's threads do not exist there). Reusing threads saves ~0.1 ms of thread
# start-up per split launch, several times per frame. Band jobs never wait on the pool, so callers
# on several threads at once cannot deadlock it.
_POOL: ThreadPoolExecutor | None = None
_POOL_PID = -1
_POOL_LOCK = threading.Lock()


def _pool() -> ThreadPoolExecutor:
    global _POOL, _POOL_PID
    with _POOL_LOCK:
        if _POOL is None or _POOL_PID != os.getpid():
            _POOL = ThreadPoolExecutor(max_workers=max(4, 2 * (os.cpu_count() or 1)),
                                       thread_name_prefix="splatsearch-bands")
            _POOL_PID = os.getpid()
        return _POOL


def run_bands(bands, n_threads: int, fn, kernel=None, device=None) -> None:
    """Call ``fn(worker, b0, b1)`` for every band; worker w takes bands w, w + n, w + 2n, ...

    The static round-robin keeps results bitwise reproducible (each worker's gradient sums run in
    a fixed order) while interleaving cheap and expensive rows. ``kernel`` is loaded first on this
    thread, so that workers never compile it concurrently.
    """
    if kernel is not None:
        kernel.module.load(wp.get_device(device))
    n_threads = max(1, min(n_threads, len(bands)))
    if n_threads == 1:
        for b0, b1 in bands:
            fn(0, b0, b1)
        return
    errors: list[BaseException] = []

    def worker(w: int) -> None:
        try:
            for b0, b1 in bands[w::n_threads]:
                fn(w, b0, b1)
        except BaseException as e:  # re-raised on the calling thread
            errors.append(e)

    pool = _pool()
    futures = [pool.submit(worker, w) for w in range(1, n_threads)]
    worker(0)
    for fu in futures:
        fu.result()
    if errors:
        raise errors[0]


def launch_split(kernel, n: int, inputs, outputs: list, device, threads: int | None = None) -> None:
    """Launch a per-element ``kernel`` over n elements; on the CPU split in contiguous chunks over
    ``threads`` workers (None: the default). ``inputs(offset, worker)`` returns the input list
    for one chunk."""
    n_threads = n_threads_for(device, threads) if n >= 4096 else 1
    bounds = [(n * w // n_threads, n * (w + 1) // n_threads) for w in range(n_threads)]

    def launch(w, a, b):
        wp.launch(kernel, dim=b - a, inputs=inputs(a, w), outputs=outputs, device=device)

    run_bands([bd for bd in bounds if bd[1] > bd[0]], n_threads, launch, kernel, device)
