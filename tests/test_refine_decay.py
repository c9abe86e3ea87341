"""``MapperConfig.refine_lr_final``: :meth:`Mapper.refine` shrinks its Adam steps towards that fraction."""

import copy

import numpy as np
import pytest

from splatsearch.mapper import Mapper, MapperConfig


@pytest.fixture(scope="module")
def fitted():
    from splatsearch.datasets import sim_trajectory

    frames, K, W, H, _ = sim_trajectory(1, 3, 96, 72)
    m = Mapper(K, W, H, MapperConfig(iters=10, stride=2, initial_capacity=4096, keyframe_every=1, exposure=True))
    for f in frames[:2]:
        m.update(f.rgb, f.depth, f.viewmat)
    return m


def _moved(m: Mapper, lr_final: float, iters: int = 12) -> float:
    """Total |change| of the Gaussian means over a refinement from the same state."""
    m = copy.deepcopy(m)
    m.cfg.refine_lr_final = lr_final
    before = np.asarray(m.map.means).copy()
    loss = m.refine(iters)
    assert np.isfinite(loss)
    return float(np.abs(np.asarray(m.map.means) - before).sum())


def test_decayed_refinement_moves_the_map_less(fitted):
    const, decayed = _moved(fitted, 1.0), _moved(fitted, 1e-3)
    assert 0 < decayed < 0.8 * const, (decayed, const)


@pytest.mark.parametrize("bad", [0.0, -0.5, 1.5])
def test_refine_lr_final_is_validated(bad):
    with pytest.raises(ValueError, match="refine_lr_final"):
        MapperConfig(refine_lr_final=bad).validate()
