"""Image losses and metrics: L1, SSIM, PSNR and the mapping loss (thesis eq 7-9)."""

from __future__ import annotations

import functools

import jax.numpy as jnp
import numpy as np


@functools.cache
def _gauss_window(size: int = 11, sigma: float = 1.5) -> np.ndarray:
    # numpy, not jnp: a cached jnp array created under a trace would leak the tracer
    x = np.arange(size, dtype=np.float32) - (size - 1) / 2
    g = np.exp(-(x**2) / (2 * sigma**2))
    return (g / g.sum()).astype(np.float32)


@functools.cache
def _local_band(block: int, size: int, sigma: float) -> np.ndarray:
    """(block, block + size - 1) matrix: row i holds the window at columns i .. i + size - 1."""
    g = _gauss_window(size, sigma)
    M = np.zeros((block, block + size - 1), np.float32)
    for i in range(block):
        M[i, i:i + size] = g
    return M


def _blur_rows(x, size: int, sigma: float, block: int = 32):
    """Gaussian blur of (N, ...) along axis 0 with zero padding.

    The axis is cut into blocks of ``block`` rows, each with a halo of ``size // 2`` rows on both
    sides, and every block is one small matrix product. A dense banded (N, N) product wastes
    N / size of its work on zeros and shifted-slice sums or XLA's convolution are slower still on
    the CPU; the halos are built from reshapes and slices so that the gradient stays cheap.
    """
    n, p = x.shape[0], size // 2
    nb = -(-n // block)
    rest = x.shape[1:]
    xp = jnp.pad(x, ((p, nb * block - n + p),) + ((0, 0),) * len(rest))
    core = xp[p:p + nb * block].reshape((nb, block) + rest)
    top = xp[:nb * block].reshape((nb, block) + rest)[:, :p]
    bottom = xp[2 * p:2 * p + nb * block].reshape((nb, block) + rest)[:, block - p:]
    windows = jnp.concatenate([top, core, bottom], 1)
    y = jnp.einsum("ij,bj...->bi...", jnp.asarray(_local_band(block, size, sigma)), windows)
    return y.reshape((nb * block,) + rest)[:n]


def _blur(x, size: int = 11, sigma: float = 1.5):
    """Separable Gaussian blur of (H, W, C) with zero padding (as the 3DGS ssim does)."""
    y = _blur_rows(x, size, sigma)
    return jnp.swapaxes(_blur_rows(jnp.swapaxes(y, 0, 1), size, sigma), 0, 1)


def ssim_stats(b, size: int = 11, sigma: float = 1.5):
    """(mu_b, sigma_bb) of a fixed target image, to reuse across :func:`ssim` calls."""
    mu_b = _blur(b, size, sigma)
    return mu_b, _blur(b * b, size, sigma) - mu_b**2


def ssim(a, b, size: int = 11, sigma: float = 1.5, b_stats=None):
    """Mean SSIM of two (H, W, C) images in [0, 1] (Gaussian window 11, sigma 1.5).

    ``b_stats`` = ``ssim_stats(b)`` skips the target's two blurs (it is constant in a fit).
    """
    c1, c2 = 0.01**2, 0.03**2
    mu_b, sbb = ssim_stats(b, size, sigma) if b_stats is None else b_stats
    C = a.shape[-1]
    blurred = _blur(jnp.concatenate([a, a * a, a * b], -1), size, sigma)  # one pass for three blurs
    mu_a = blurred[..., :C]
    saa = blurred[..., C:2 * C] - mu_a**2
    sab = blurred[..., 2 * C:] - mu_a * mu_b
    m = ((2 * mu_a * mu_b + c1) * (2 * sab + c2)) / ((mu_a**2 + mu_b**2 + c1) * (saa + sbb + c2))
    return jnp.mean(m)


def l1(a, b, mask=None):
    """Mean absolute error, over ``mask`` (broadcastable bool) if given."""
    d = jnp.abs(a - b)
    if mask is None:
        return jnp.mean(d)
    m = jnp.broadcast_to(mask, d.shape).astype(d.dtype)
    return jnp.sum(d * m) / jnp.maximum(jnp.sum(m), 1.0)


def psnr(a, b, mask=None):
    """PSNR in dB of images in [0, 1]."""
    d = (a - b) ** 2
    if mask is None:
        mse = jnp.mean(d)
    else:
        m = jnp.broadcast_to(mask, d.shape).astype(d.dtype)
        mse = jnp.sum(d * m) / jnp.maximum(jnp.sum(m), 1.0)
    return -10.0 * jnp.log10(jnp.maximum(mse, 1e-12))


def mapping_loss(image, depth, rgb_obs, depth_obs, *, lambda_p: float = 0.5, w_l1: float = 0.8,
                 lambda_g: float = 1.0, rgb_stats=None):
    """Eq 7-9: lambda_p (w L1 + (1 - w)(1 - SSIM)) on colour + lambda_g L1 on valid depth.

    image, rgb_obs: (H, W, 3); depth: (H, W, 1) rendered; depth_obs: (H, W) metres, 0 = invalid;
    rgb_stats: optional ``ssim_stats(rgb_obs)``.
    """
    valid = (depth_obs > 0)[..., None]
    photo = w_l1 * l1(image, rgb_obs) + (1.0 - w_l1) * (1.0 - ssim(image, rgb_obs, b_stats=rgb_stats))
    geo = l1(depth, depth_obs[..., None], valid)
    return lambda_p * photo + lambda_g * geo
