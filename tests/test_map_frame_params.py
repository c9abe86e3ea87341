"""Per-frame parameters optimised with the map: keyframe pose refinement and affine exposure."""

import jax.numpy as jnp
import numpy as np
import pytest

from splatsearch.mapper import Mapper, MapperConfig
from splatsearch.slam import SLAM, TrackerConfig, perturb_viewmat, pose_distance


@pytest.fixture(scope="module")
def walk():
    from splatsearch.datasets import sim_trajectory

    frames, K, W, H, _ = sim_trajectory(1, 3, 96, 72)
    return frames, K, W, H


def _mapper(walk, **kw):
    frames, K, W, H = walk
    m = Mapper(K, W, H, MapperConfig(iters=20, stride=1, initial_capacity=8192, keyframe_every=1, **kw))
    f0 = frames[0]
    for _ in range(3):
        m.update(f0.rgb, f0.depth, f0.viewmat)
    return m


def test_pose_refinement_pulls_a_wrong_keyframe_pose_back(walk):
    frames, *_ = walk
    f1 = frames[1]  # same place as frame 0, turned by 6 degrees
    m = _mapper(walk, pose_refine=True, pose_lr_rot=5e-4, pose_lr_trans=5e-4)
    xi = jnp.array([0.005, -0.006, 0.004, 0.008, -0.006, 0.008])
    noisy = np.asarray(perturb_viewmat(jnp.asarray(f1.viewmat), xi))
    ang0, d0 = pose_distance(noisy, f1.viewmat)
    st = m.update(f1.rgb, f1.depth, noisy, refine_pose=True, tag=7)
    assert set(st["poses"]) == {7}
    m.refine(100)
    ang, d = pose_distance(m.keyframes[-1].viewmat, f1.viewmat)
    assert ang < 0.3 * ang0 and d < 0.5 * d0, (ang0, d0, ang, d)
    # frames given as ground truth (refine_pose False) and the first frame never move
    np.testing.assert_array_equal(m.keyframes[0].viewmat, frames[0].viewmat.astype(np.float32))
    assert np.isfinite(np.asarray(m.map.means)[: m.map.n_active]).all()


def test_pose_refinement_off_leaves_poses_alone(walk):
    frames, *_ = walk
    m = _mapper(walk)
    noisy = np.asarray(perturb_viewmat(jnp.asarray(frames[1].viewmat), jnp.array([0.0, 0.0, 0.0, 0.01, 0.0, 0.0])))
    st = m.update(frames[1].rgb, frames[1].depth, noisy, refine_pose=True, tag=1)
    np.testing.assert_array_equal(st["viewmat"], noisy.astype(np.float32))
    assert st["poses"] == {1: st["viewmat"]}


def test_exposure_gain_follows_a_darker_frame(walk):
    frames, *_ = walk
    m = _mapper(walk, exposure=True)
    f0 = frames[0]
    m.update(np.clip(f0.rgb * 0.8, 0, 1), f0.depth, f0.viewmat)
    m.refine(60)
    gain0, bias0 = m.keyframes[0].exposure
    assert (gain0, bias0) == (1.0, 0.0)  # the first frame sets the colour scale
    gain, bias = m.keyframes[-1].exposure
    mid = float(np.mean(f0.rgb))
    assert gain * mid + bias < 0.95 * mid, (gain, bias)  # the dark frame is explained by its exposure
    darker = m.evaluate([m.keyframes[-1]], exposure=True)["psnr"]
    assert darker > m.evaluate([m.keyframes[-1]])["psnr"]


def test_slam_writes_refined_poses_into_the_trajectory(walk):
    frames, K, W, H = walk
    s = SLAM(K, W, H, MapperConfig(iters=10, stride=1, initial_capacity=8192, keyframe_every=1, pose_refine=True),
             TrackerConfig(iters=10))
    for i, f in enumerate(frames):
        s.process(f.rgb, f.depth, f.viewmat if i == 0 else None)
    s.refine(20)
    traj = s.trajectory()
    assert traj.shape == (3, 4, 4) and np.isfinite(traj).all()
    np.testing.assert_array_equal(traj[0], frames[0].viewmat.astype(np.float32))  # the given first pose stays
    for kf in s.mapper.keyframes[1:]:
        np.testing.assert_array_equal(traj[kf.tag], kf.viewmat)
