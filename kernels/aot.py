"""Every Warp module the library launches, for ahead-of-time CUDA compilation.

``wp.compile_aot_module(module, arch=...)`` builds a module for a GPU architecture through NVRTC
without a GPU or a CUDA driver; the test suite does it for sm_80 and sm_90 on every change, so a
CUDA codegen or compile error shows up on a CPU-only machine. Kernels generated per colour-channel
count are listed for the channel counts the library renders with (1 for depth-only, 3 for RGB).
"""

from __future__ import annotations

import importlib
from collections.abc import Iterable

import warp as wp

#: modules whose module-level ``@wp.kernel`` functions are launched by the library
KERNEL_MODULES = (
    "splatsearch.kernels.projection",
    "splatsearch.kernels.binning",
    "splatsearch.kernels.composite",
    "splatsearch.kernels.densify",
    "splatsearch.kernels.validate",
    "splatsearch.kernels.pipeline",
    "splatsearch.sim.raycast",
    "splatsearch.sim.episodes",
    "splatsearch.sim.navgrid",
)


def generated_kernels(channels: Iterable[int] = (1, 3)) -> list:
    """Kernels built by factories per channel count C (each lives in a module of its own)."""
    from .composite import composite_kernels, composite_pose_kernels, composite_tile_kernels

    out = []
    for C in channels:
        out += list(composite_kernels(C)) + list(composite_tile_kernels(C)) + list(composite_pose_kernels(C))
    return out


def warp_modules(channels: Iterable[int] = (1, 3)) -> dict:
    """``{name: wp Module}`` of every module-level and generated kernel the library launches."""
    mods = {}
    for name in KERNEL_MODULES:
        py_mod = importlib.import_module(name)
        for obj in vars(py_mod).values():
            if isinstance(obj, wp.Kernel) and obj.module is not None:
                mods.setdefault(obj.module.name, obj.module)
    for k in generated_kernels(channels):
        mods.setdefault(k.module.name, k.module)
    return mods


def nvrtc_archs() -> set[int]:
    """GPU architectures this Warp build's NVRTC can compile for (empty when NVRTC is absent)."""
    wp.init()
    try:
        from warp._src.context import runtime  # Warp >= 1.10 keeps the runtime here
    except ImportError:  # pragma: no cover - older layouts
        runtime = getattr(getattr(wp, "context", None), "runtime", None)
    return set(getattr(runtime, "nvrtc_supported_archs", None) or ())


def compile_cuda(archs: Iterable[int] = (80, 90), module_dir: str | None = None,
                 channels: Iterable[int] = (1, 3)) -> dict[str, list]:
    """Compile every module for every arch (cubin); returns ``{module name: [artifact paths]}``.
    Raises whatever Warp raises on a codegen or NVRTC error."""
    out = {}
    for name, mod in warp_modules(channels).items():
        out[name] = []
        for arch in archs:
            out[name] += wp.compile_aot_module(mod, arch=arch, module_dir=module_dir, use_ptx=False)
    return out
