"""Every Warp module of the library compiles for CUDA (sm_80 and sm_90) through NVRTC.

No GPU or CUDA driver is needed: ``wp.compile_aot_module`` runs Warp's CUDA code generation and
NVRTC and writes cubins to a temporary folder. A CUDA codegen or compile error fails the test;
where this Warp build has no NVRTC (or NVRTC lacks the architecture) the tests skip with the reason.
About 20 s on 2 busy cores for all modules and both architectures.
"""

import pytest
import warp as wp

from splatsearch.kernels import aot

ARCHS = (80, 90)
MODULES = aot.warp_modules()


def _require_nvrtc(arch: int) -> None:
    archs = aot.nvrtc_archs()
    if not archs:
        pytest.skip("this Warp build has no NVRTC: CUDA kernels cannot be compiled here")
    if arch not in archs:
        pytest.skip(f"NVRTC here cannot target sm_{arch} (supports {sorted(archs)})")


@pytest.fixture(scope="module")
def out_dir(tmp_path_factory):
    return str(tmp_path_factory.mktemp("cuda_aot"))


def test_module_list_covers_the_pipeline():
    names = set(MODULES)
    for expected in ("splatsearch.kernels.projection", "splatsearch.kernels.binning",
                     "splatsearch.kernels.pipeline", "splatsearch.kernels.densify", "splatsearch.sim.raycast"):
        assert expected in names
    assert sum("composite" in n for n in names) >= 2 * len(aot.generated_kernels((1,)))


@pytest.mark.parametrize("arch", ARCHS)
@pytest.mark.parametrize("name", sorted(MODULES))
def test_module_compiles_for_cuda(name, arch, out_dir):
    _require_nvrtc(arch)
    paths = wp.compile_aot_module(MODULES[name], arch=arch, module_dir=out_dir, use_ptx=False)
    assert paths and all(p.exists() and p.stat().st_size > 0 for p in paths)
    assert all(f"sm{arch}" in p.name for p in paths)


@wp.func_native("""
    return this is not valid CUDA;
""")
def _broken_native(x: float) -> float: ...


@wp.kernel(module="unique", enable_backward=False)
def _broken_kernel(a: wp.array(dtype=float)):
    i = wp.tid()
    a[i] = _broken_native(a[i])


def test_a_cuda_compile_error_fails(out_dir):
    """The harness is not vacuous: NVRTC errors surface as exceptions."""
    _require_nvrtc(80)
    with pytest.raises(Exception):
        wp.compile_aot_module(_broken_kernel.module, arch=80, module_dir=out_dir, use_ptx=False)
