"""MapperConfig.pose_lr_trans_loose: a larger refinement translation step for frames that no
frame-to-frame step anchored (Mapper.update(loose=True)); off by default."""

import jax.numpy as jnp
import numpy as np
import pytest

from splatsearch.mapper import Mapper, MapperConfig
from splatsearch.slam import perturb_viewmat, pose_distance


@pytest.fixture(scope="module")
def walk():
    from splatsearch.datasets import sim_trajectory

    frames, K, W, H, _ = sim_trajectory(1, 3, 96, 72)
    return frames, K, W, H


def _refined_translation_error(walk, loose: bool, **kw) -> tuple[float, float]:
    frames, K, W, H = walk
    m = Mapper(K, W, H, MapperConfig(iters=20, stride=1, initial_capacity=8192, keyframe_every=1, pose_refine=True,
                                     pose_lr_rot=1e-9, **kw))
    for _ in range(3):
        m.update(frames[0].rgb, frames[0].depth, frames[0].viewmat)
    f1 = frames[1]
    noisy = np.asarray(perturb_viewmat(jnp.asarray(f1.viewmat), jnp.array([0.0, 0.0, 0.0, 0.01, -0.008, 0.01])))
    d0 = pose_distance(noisy, f1.viewmat)[1]
    m.update(f1.rgb, f1.depth, noisy, refine_pose=True, tag=1, loose=loose)
    m.refine(40)
    return d0, pose_distance(m.keyframes[-1].viewmat, f1.viewmat)[1]


def test_validation():
    with pytest.raises(ValueError, match="pose_lr_trans_loose"):
        MapperConfig(pose_lr_trans_loose=0.0).validate()
    MapperConfig(pose_lr_trans_loose=2e-4).validate()
    assert MapperConfig().pose_lr_trans_loose is None


def test_loose_frames_take_the_larger_step(walk):
    d0, tight = _refined_translation_error(walk, loose=True, pose_lr_trans=1e-6)  # loose unset: the small step
    _, loose = _refined_translation_error(walk, loose=True, pose_lr_trans=1e-6, pose_lr_trans_loose=5e-4)
    _, anchored = _refined_translation_error(walk, loose=False, pose_lr_trans=1e-6, pose_lr_trans_loose=5e-4)
    # 40+ steps of 1e-6 m cannot move a 1.6 cm error; 5e-4 m steps pull it well back
    assert tight > 0.95 * d0 and anchored > 0.95 * d0, (d0, tight, anchored)
    assert loose < 0.6 * d0, (d0, loose)
