"""Defaults of the rasterizer's run-time choices, and the one place that reads their environment
variables.

Every choice is an argument (``composite=``, ``threads=`` of :func:`splatsearch.rasterize` and of
the pipeline functions); ``None`` there means "the default", which is resolved here at call time:

* ``SPLATSEARCH_COMPOSITE`` = ``tile`` | ``pixel``: compositing kernel. Default ``tile`` on the
  CPU (one thread per 16x16 tile walking exact ellipse spans), ``pixel`` on CUDA (one thread per
  pixel, the GPU layout). Both give the same images and gradients.
* ``SPLATSEARCH_THREADS`` = n >= 1: CPU worker threads of a launch. Default: the usable cores.
"""

from __future__ import annotations

import os

import warp as wp

COMPOSITE_ENV = "SPLATSEARCH_COMPOSITE"
THREADS_ENV = "SPLATSEARCH_THREADS"
COMPOSITE_VARIANTS = ("tile", "pixel")


def usable_cores() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


_process_threads: int | None = None  # set_default_threads(): a worker's share of the machine


def set_default_threads(threads: int | None) -> None:
    """Make ``threads`` this process's default CPU thread count (before the environment variable);
    None removes it. For worker processes that get a share of the cores (splatsearch.parallel)."""
    global _process_threads
    if threads is not None and (isinstance(threads, bool) or int(threads) < 1):
        raise ValueError(f"threads must be >= 1, got {threads!r}")
    _process_threads = None if threads is None else int(threads)


def default_threads() -> int:
    """:func:`set_default_threads`'s value if set, else ``SPLATSEARCH_THREADS`` (>= 1), else the
    usable core count."""
    if _process_threads is not None:
        return _process_threads
    env = os.environ.get(THREADS_ENV, "").strip()
    if env:
        try:
            return max(1, int(env))
        except ValueError:
            raise ValueError(f"{THREADS_ENV} must be a positive integer, got {env!r}") from None
    return usable_cores()


def default_composite(device) -> str:
    """``SPLATSEARCH_COMPOSITE`` if set, else "tile" on the CPU and "pixel" on CUDA."""
    env = os.environ.get(COMPOSITE_ENV, "").strip().lower()
    if env:
        if env not in COMPOSITE_VARIANTS:
            raise ValueError(f"{COMPOSITE_ENV} must be one of {COMPOSITE_VARIANTS}, got {env!r}")
        return env
    return "tile" if wp.get_device(device).is_cpu else "pixel"


def resolve_composite(composite: str | None, device) -> str:
    """The compositing kernel to use: ``composite`` if given (validated), else the default."""
    if composite is None:
        return default_composite(device)
    if composite not in COMPOSITE_VARIANTS:
        raise ValueError(f"composite must be one of {COMPOSITE_VARIANTS} or None, got {composite!r}")
    return composite


def resolve_threads(threads: int | None, device) -> int:
    """Worker threads for a launch on ``device``: 1 on CUDA; on the CPU ``threads`` if given
    (>= 1), else the default."""
    if threads is not None and (isinstance(threads, bool) or int(threads) != threads or threads < 1):
        raise ValueError(f"threads must be a positive integer or None, got {threads!r}")
    if not wp.get_device(device).is_cpu:
        return 1
    return int(threads) if threads is not None else default_threads()
