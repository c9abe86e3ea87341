"""rasterization(): gsplat's call and return form over splatsearch.rasterize."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scenes import H, W, camera, intrinsics, look_at, random_scene

import splatsearch
from splatsearch.gsplat import SH_C0, rasterization, spherical_harmonics


def _cams():
    vm0, K = camera()
    vm1 = look_at([1.0, -2.5, 0.8], [0.0, 0.0, 0.0])
    return np.stack([vm0, vm1]).astype(np.float32), np.stack([K, intrinsics(f=55.0)]).astype(np.float32)


def test_matches_rasterize_and_returns_gsplat_shapes():
    means, quats, scales, opac, colors = random_scene(0)
    vms, Ks = _cams()
    rc, ra, meta = rasterization(means, quats, scales, opac, colors, vms, Ks, W, H,
                                             render_mode="RGB+ED")
    assert rc.shape == (2, H, W, 4) and ra.shape == (2, H, W, 1)
    ref = splatsearch.rasterize(means, quats, scales, opac, colors, vms, Ks, W, H, render_mode="RGB+ED")
    np.testing.assert_allclose(np.asarray(rc[..., :3]), np.asarray(ref.image), atol=1e-6)
    np.testing.assert_allclose(np.asarray(rc[..., 3:]), np.asarray(ref.depth), atol=1e-6)
    np.testing.assert_allclose(np.asarray(ra), np.asarray(ref.alpha), atol=1e-6)
    assert meta["means2d"].shape == (2, len(means), 2) and meta["radii"].shape == (2, len(means), 2)
    assert meta["n_cameras"] == 2 and meta["width"] == W and meta["height"] == H
    # means2d is the pinhole projection of the means
    cam = means @ vms[1, :3, :3].T + vms[1, :3, 3]
    u = Ks[1, 0, 0] * cam[:, 0] / cam[:, 2] + Ks[1, 0, 2]
    np.testing.assert_allclose(np.asarray(meta["means2d"][1, :, 0]), u, rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(np.asarray(meta["depths"][1]), cam[:, 2], rtol=1e-5)
    for mode, x in (("RGB", 3), ("D", 1), ("ED", 1), ("RGB+D", 4)):
        rc, _, _ = rasterization(means, quats, scales, opac, colors, vms, Ks, W, H, render_mode=mode)
        assert rc.shape == (2, H, W, x), mode


def test_per_camera_colors_and_backgrounds():
    means, quats, scales, opac, colors = random_scene(1)
    vms, Ks = _cams()
    per_cam = np.stack([colors, 1 - colors])
    bg = np.array([[0, 0, 1], [1, 0, 0]], np.float32)
    rc, _, _ = rasterization(means, quats, scales, opac, per_cam, vms, Ks, W, H, backgrounds=bg)
    for c in range(2):
        ref = splatsearch.rasterize(means, quats, scales, opac, per_cam[c], vms[c], Ks[c], W, H, render_mode="RGB",
                                    backgrounds=bg[c])
        np.testing.assert_allclose(np.asarray(rc[c]), np.asarray(ref.image), atol=1e-6)


def _sh_reference(deg, d, c):
    """Straight transcription of the 3DGS eval_sh for one direction, in float64."""
    d = d / np.linalg.norm(d)
    x, y, z = d
    b = [0.28209479177387814]
    if deg >= 1:
        b += [-0.4886025119029199 * y, 0.4886025119029199 * z, -0.4886025119029199 * x]
    if deg >= 2:
        b += [1.0925484305920792 * x * y, -1.0925484305920792 * y * z, 0.31539156525252005 * (2 * z * z - x * x - y * y),
              -1.0925484305920792 * x * z, 0.5462742152960396 * (x * x - y * y)]
    if deg >= 3:
        b += [-0.5900435899266435 * y * (3 * x * x - y * y), 2.890611442640554 * x * y * z,
              -0.4570457994644658 * y * (4 * z * z - x * x - y * y),
              0.3731763325901154 * z * (2 * z * z - 3 * x * x - 3 * y * y),
              -0.4570457994644658 * x * (4 * z * z - x * x - y * y), 1.445305721320277 * z * (x * x - y * y),
              -0.5900435899266435 * x * (x * x - 3 * y * y)]
    return np.asarray(b) @ c[: len(b)]


@pytest.mark.parametrize("deg", [0, 1, 2, 3])
def test_spherical_harmonics_match_the_3dgs_formula(deg):
    rng = np.random.default_rng(deg)
    d = rng.normal(size=(5, 3))
    c = rng.normal(size=(5, 16, 3))
    got = np.asarray(spherical_harmonics(deg, jnp.asarray(d), jnp.asarray(c)))
    ref = np.stack([_sh_reference(deg, d[i], c[i]) for i in range(5)])
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-6)


def test_sh_degree_0_renders_like_plain_colours_and_higher_degrees_depend_on_view():
    means, quats, scales, opac, colors = random_scene(2)
    vms, Ks = _cams()
    sh = np.zeros((len(means), 16, 3), np.float32)
    sh[:, 0] = (colors - 0.5) / SH_C0
    a, _, _ = rasterization(means, quats, scales, opac, sh, vms, Ks, W, H, sh_degree=0)
    b, _, _ = rasterization(means, quats, scales, opac, colors, vms, Ks, W, H)
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-5)
    sh[:, 1:4] = 0.5
    c, _, _ = rasterization(means, quats, scales, opac, sh, vms, Ks, W, H, sh_degree=1)
    assert np.abs(np.asarray(c) - np.asarray(b)).max() > 0.01


def test_gradients_reach_means_through_image_and_means2d():
    means, quats, scales, opac, colors = random_scene(3)
    vms, Ks = _cams()

    def loss(m):
        rc, _, meta = rasterization(m, quats, scales, opac, colors, vms, Ks, W, H)
        return rc.mean() + 1e-3 * meta["means2d"].mean()

    g = jax.grad(loss)(jnp.asarray(means))
    assert g.shape == means.shape and np.isfinite(np.asarray(g)).all() and np.abs(np.asarray(g)).max() > 0


def test_unsupported_gsplat_options_are_named():
    means, quats, scales, opac, colors = random_scene(0)
    vms, Ks = _cams()
    with pytest.raises(NotImplementedError, match="packed"):
        rasterization(means, quats, scales, opac, colors, vms, Ks, W, H, packed=False)
    rasterization(means, quats, scales, opac, colors, vms, Ks, W, H, packed=True)  # the default is fine
    with pytest.raises(TypeError, match="bogus"):
        rasterization(means, quats, scales, opac, colors, vms, Ks, W, H, bogus=1)
    with pytest.raises(ValueError, match="viewmats"):
        rasterization(means, quats, scales, opac, colors, vms[0], Ks, W, H)
