"""``slam.trusted_pixels``: the one definition of the pixels tracking trusts (the tracker's stages and
``slam.pose_jacobian`` both use it)."""

import jax.numpy as jnp
import numpy as np

from splatsearch.slam import trusted_pixels


def _reference(alpha, d_err, depth, sil, k):
    m = (alpha > sil) & (depth > 0)
    if k > 0:
        m &= d_err <= k * np.median(d_err[m])
    return m.astype(np.float32)


def test_silhouette_valid_depth_and_outliers():
    rng = np.random.default_rng(0)
    H, W = 12, 16
    alpha = rng.uniform(0.95, 1.0, (H, W)).astype(np.float32)
    depth = rng.uniform(0.5, 3.0, (H, W)).astype(np.float32)
    depth[0, :4] = 0.0  # no depth: never trusted
    d_err = rng.uniform(0.0, 0.01, (H, W)).astype(np.float32)
    d_err[5, 5] = 1.0  # a depth edge: 100x the typical error
    m = np.asarray(trusted_pixels(jnp.asarray(alpha), jnp.asarray(d_err), jnp.asarray(depth), 0.99, 10.0))
    assert m.dtype == np.float32 and m.shape == (H, W)
    np.testing.assert_array_equal(m, _reference(alpha, d_err, depth, 0.99, 10.0))
    assert not m[0, :4].any()
    assert not m[alpha <= 0.99].any()
    assert m[5, 5] == 0.0 or alpha[5, 5] <= 0.99
    # outlier_k 0 keeps the outlier (only coverage and valid depth count)
    m0 = np.asarray(trusted_pixels(jnp.asarray(alpha), jnp.asarray(d_err), jnp.asarray(depth), 0.99, 0.0))
    np.testing.assert_array_equal(m0, ((alpha > 0.99) & (depth > 0)).astype(np.float32))


def test_nothing_covered_gives_an_empty_mask_not_nan():
    z = jnp.zeros((4, 5), jnp.float32)
    m = np.asarray(trusted_pixels(z, z, jnp.ones((4, 5)), 0.99, 10.0))
    assert m.sum() == 0 and np.all(np.isfinite(m))
