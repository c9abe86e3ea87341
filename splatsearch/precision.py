"""Full float32 matmul precision for the geometry paths (mapping, tracking, projection).

On NVIDIA GPUs since Ampere, XLA runs a float32 ``dot`` as TF32 (a 10-bit mantissa) unless told
otherwise. Harmless for the neural networks, it is ruinous for camera geometry: measured on an
H200, it moved projected means by 0.01-0.05 px and cost TUM fr1/xyz mapping 2-3 dB of PSNR (see
docs/performance.md, "CUDA"). The mapper's and the tracker's jitted steps and the pose algebra
(``so3_exp``, ``perturb_viewmat``, ``planar_basis``) are therefore traced under
:func:`full_precision`; on the CPU it changes nothing.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TypeVar

import jax

F = TypeVar("F", bound=Callable)


def full_precision(fn: F) -> F:
    """``fn`` traced with every float32 matmul and einsum at ``jax.lax.Precision.HIGHEST``.

    Apply it inside ``jax.jit`` (``jax.jit(full_precision(f))``): the precision is fixed in the
    traced program, so it holds wherever and however often the compiled function is called.
    """

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        with jax.default_matmul_precision("highest"):
            return fn(*args, **kwargs)

    return wrapped  # type: ignore[return-value]
