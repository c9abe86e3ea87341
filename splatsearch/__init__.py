"""splatsearch: differentiable 3D Gaussian Splatting mapping and object search for robots.

The rasterizer is the foundation: :func:`rasterize` renders Gaussians with Warp kernels on CPU
or CUDA, under ``jax.jit`` and ``jax.grad``.
"""

from splatsearch.rasterization import RENDER_MODES, RasterOutput, rasterize, rasterize_top_ids

__version__ = "0.1.0"
__all__ = ["RENDER_MODES", "RasterOutput", "rasterize", "rasterize_top_ids", "__version__"]
