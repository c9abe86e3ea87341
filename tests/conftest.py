import os
import sys

import jax

jax.config.update("jax_enable_x64", True)  # the reference runs in float64; splatsearch casts to float32
sys.path.insert(0, os.path.dirname(__file__))
# the CLI turns on JAX's on-disk compilation cache; tests stay hermetic and leave $HOME alone
os.environ.setdefault("SPLATSEARCH_JAX_CACHE", "off")


import numpy as np  # noqa: E402
import pytest  # noqa: E402


@pytest.fixture(params=["tile", "pixel"])
def variant(request, monkeypatch):
    """Run a test with both compositing kernels: per-tile (CPU default) and per-pixel (CUDA default)."""
    monkeypatch.setenv("SPLATSEARCH_COMPOSITE", request.param)
    return request.param


@pytest.fixture(scope="module")
def tracking_walk():
    """Three frames of a simulator walk at 96x72: (frames, K, W, H)."""
    from splatsearch.datasets import sim_trajectory

    frames, K, W, H, _ = sim_trajectory(1, 3, 96, 72)
    return frames, K, W, H


@pytest.fixture(scope="module")
def tracking_map(tracking_walk):
    """A mapper fitted to the walk's first frame (3 x 20 steps) and that frame, for tracking tests."""
    from splatsearch.mapper import Mapper, MapperConfig

    frames, K, W, H = tracking_walk
    f = frames[0]
    m = Mapper(K, W, H, MapperConfig(iters=20, stride=1, initial_capacity=8192))
    for _ in range(3):
        m.update(f.rgb, f.depth, f.viewmat)
    return m, f


@pytest.fixture
def random_blob_map():
    """Factory of a small Gaussian map (the ``render_args()`` tuple): ``n`` isotropic blobs of
    radius ``scale`` metres (3 cm) with random colours, uniform in a cube of half-side ``extent``
    metres (0.3) around ``centre``, all of opacity ``opacity``; seeded."""
    import numpy as np

    def make(opacity: float = 0.9, n: int = 400, seed: int = 0, centre=(0.0, 0.0, 0.0), extent: float = 0.3,
             scale: float = 0.03):
        rng = np.random.default_rng(seed)
        means = (rng.uniform(-extent, extent, (n, 3)) + np.asarray(centre)).astype(np.float32)
        return (means, np.tile(np.float32([1, 0, 0, 0]), (n, 1)), np.full((n, 3), scale, np.float32),
                np.full(n, opacity, np.float32), rng.uniform(0, 1, (n, 3)).astype(np.float32))

    return make


@pytest.fixture
def tracker_start(monkeypatch):
    """Stop ``SLAM.process`` at its tracking call and record what the tracker was handed.

    Returns a dict filled on the call: ``init`` (4x4 float64 viewmat the tracker starts from) and
    ``q`` (the 6x6 prior precision); the call raises ``RuntimeError("stop")``. Mapping is a no-op.
    """
    from splatsearch import slam

    seen: dict = {}

    def fake_track(gmap, rgb, depth, init_viewmat, K, width, height, config=None, *, prior_precision=None, **kw):
        seen["init"], seen["q"] = np.asarray(init_viewmat, np.float64), prior_precision
        raise RuntimeError("stop")

    monkeypatch.setattr(slam, "track", fake_track)
    monkeypatch.setattr(slam.Mapper, "update", lambda self, *a, **k: {})
    return seen
