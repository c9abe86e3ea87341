"""splatsearch: differentiable 3D Gaussian Splatting mapping and object search for robots.

The rasterizer is the foundation: :func:`rasterize` renders Gaussians with Warp kernels on CPU
or CUDA, under ``jax.jit`` and ``jax.grad``. Its names load on first use, so that importing a
light submodule (the command-line parser) does not import JAX or Warp.
"""

from __future__ import annotations

__version__ = "0.1.0"
__all__ = ["RENDER_MODES", "RasterOutput", "rasterize", "rasterize_top_ids", "__version__"]
_RASTER_NAMES = ("RENDER_MODES", "RasterOutput", "rasterize", "rasterize_top_ids")


def __getattr__(name: str):
    if name in _RASTER_NAMES:
        from splatsearch import rasterization

        value = getattr(rasterization, name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'splatsearch' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_RASTER_NAMES))
