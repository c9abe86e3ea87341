"""splatsearch: differentiable 3D Gaussian Splatting mapping and object search for robots.

The rasterizer is the foundation: :func:`rasterize` renders Gaussians with Warp kernels on CPU
or CUDA, under ``jax.jit`` and ``jax.grad``; ``splatsearch.gsplat.rasterization`` is the same with
gsplat's call and return form (``from splatsearch.gsplat import rasterization``).

The public names are imported on first use, so that ``import splatsearch.cli`` (and
``splatsearch --help``) does not pay for loading JAX and Warp.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from splatsearch._version import __version__

_LAZY = {
    "RENDER_MODES": "splatsearch.rasterization",
    "RasterOutput": "splatsearch.rasterization",
    "rasterize": "splatsearch.rasterization",
    "rasterize_top_ids": "splatsearch.rasterization",
}

__all__ = ["RENDER_MODES", "RasterOutput", "rasterize", "rasterize_top_ids", "__version__"]

if TYPE_CHECKING:
    from splatsearch.rasterization import RENDER_MODES, RasterOutput, rasterize, rasterize_top_ids


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'splatsearch' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
