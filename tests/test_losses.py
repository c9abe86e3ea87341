"""Image losses against independent SciPy/numpy implementations."""

import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage

from splatsearch.losses import _blur, l1, mapping_loss, psnr, ssim


def _np_ssim(a, b):
    """3DGS-style SSIM: Gaussian window 11, sigma 1.5, zero padding, per channel, float64."""
    x = np.arange(11) - 5.0
    g = np.exp(-x**2 / (2 * 1.5**2))
    g /= g.sum()

    def blur(img):
        out = ndimage.correlate1d(img, g, axis=0, mode="constant")
        return ndimage.correlate1d(out, g, axis=1, mode="constant")

    a, b = a.astype(np.float64), b.astype(np.float64)
    mu_a, mu_b = blur(a), blur(b)
    saa, sbb, sab = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2, blur(a * b) - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    m = ((2 * mu_a * mu_b + c1) * (2 * sab + c2)) / ((mu_a**2 + mu_b**2 + c1) * (saa + sbb + c2))
    return m.mean()


@pytest.mark.parametrize("shape", [(240, 320, 3), (37, 50, 2), (64, 64, 1), (5, 9, 3)])
def test_blur_matches_scipy(shape):
    x = np.random.default_rng(0).random(shape).astype(np.float32)
    g = np.exp(-(np.arange(11) - 5.0) ** 2 / (2 * 1.5**2))
    g /= g.sum()
    ref = ndimage.correlate1d(ndimage.correlate1d(x.astype(np.float64), g, axis=0, mode="constant"), g, axis=1,
                              mode="constant")
    np.testing.assert_allclose(np.asarray(_blur(jnp.asarray(x))), ref, atol=1e-5)


def test_ssim_matches_numpy_reference():
    rng = np.random.default_rng(1)
    b = rng.random((60, 80, 3)).astype(np.float32)
    a = np.clip(b + rng.normal(0, 0.1, b.shape), 0, 1).astype(np.float32)
    assert float(ssim(jnp.asarray(a), jnp.asarray(b))) == pytest.approx(_np_ssim(a, b), abs=1e-5)
    assert float(ssim(jnp.asarray(b), jnp.asarray(b))) == pytest.approx(1.0, abs=1e-6)


def test_l1_psnr_and_mapping_loss_by_hand():
    a = jnp.zeros((4, 4, 3), jnp.float32)
    b = jnp.full((4, 4, 3), 0.1, jnp.float32)
    assert float(l1(a, b)) == pytest.approx(0.1, rel=1e-6)
    assert float(psnr(a, b)) == pytest.approx(20.0, rel=1e-5)
    depth_obs = jnp.zeros((4, 4), jnp.float32).at[:2].set(2.0)  # half the pixels valid
    depth = jnp.full((4, 4, 1), 1.5, jnp.float32)
    # identical images: only the depth term remains, over valid pixels only
    assert float(mapping_loss(b, depth, b, depth_obs)) == pytest.approx(0.5, rel=1e-5)
