"""Warp kernels of splatsearch: projection, tile binning, compositing (forward and hand-written
backward) and their host-side orchestration. The same kernels run on ``cpu`` and ``cuda``."""

import warp as _wp

_wp.config.quiet = True
# per-module "load on device" timings are Warp's INFO logs: too chatty for a library's users
_wp.config.log_level = getattr(_wp, "LOG_WARNING", _wp.config.log_level)

from .parallel import cpu_threads, launch_split, run_bands  # noqa: E402
from .pipeline import (  # noqa: E402
    TILE_SIZE,
    Workspace,
    bin_gaussians,
    count_evaluations,
    grid_dims,
    project,
    rasterize_backward,
    rasterize_forward,
)

__all__ = [
    "TILE_SIZE",
    "Workspace",
    "bin_gaussians",
    "count_evaluations",
    "cpu_threads",
    "grid_dims",
    "launch_split",
    "run_bands",
    "project",
    "rasterize_backward",
    "rasterize_forward",
]
