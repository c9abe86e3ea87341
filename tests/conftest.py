import os
import sys

import jax

jax.config.update("jax_enable_x64", True)  # the reference runs in float64; splatsearch casts to float32
sys.path.insert(0, os.path.dirname(__file__))
# the CLI turns on JAX's on-disk compilation cache; tests stay hermetic and leave $HOME alone
os.environ.setdefault("SPLATSEARCH_JAX_CACHE", "off")


import pytest  # noqa: E402


@pytest.fixture(params=["tile", "pixel"])
def variant(request, monkeypatch):
    """Run a test with both compositing kernels: per-tile (CPU default) and per-pixel (CUDA default)."""
    monkeypatch.setenv("SPLATSEARCH_COMPOSITE", request.param)
    return request.param
