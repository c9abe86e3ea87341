"""splatsearch: differentiable 3D Gaussian Splatting mapping and object search for robots.

The rasterizer is the foundation: :func:`rasterize` renders Gaussians with Warp kernels on CPU
or CUDA, under ``jax.jit`` and ``jax.grad``; ``splatsearch.gsplat.rasterization`` is the same with
gsplat's call and return form (``from splatsearch.gsplat import rasterization``).

The public names are imported on first use, so that ``import splatsearch.cli`` (and
``splatsearch --help``) does not pay for loading JAX and Warp.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from splatsearch._lazy import lazy_exports
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


__getattr__, __dir__ = lazy_exports(__name__, _LAZY, globals())
