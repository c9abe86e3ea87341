"""PLY interoperability: INRIA's loader accepts our maps; ASCII, big-endian and SH files load."""

import numpy as np
import pytest

from splatsearch import io
from splatsearch.gaussians import empty_map


def _map(n=7, seed=0):
    rng = np.random.default_rng(seed)
    g = empty_map(n + 3)
    act = np.r_[np.ones(n, bool), np.zeros(3, bool)]
    return g.replace(means=g.means.at[:].set(rng.normal(size=(n + 3, 3)).astype(np.float32)),
                     colors=g.colors.at[:].set(rng.uniform(0, 1, (n + 3, 3)).astype(np.float32)),
                     log_scales=g.log_scales.at[:].set(rng.uniform(-4, -1, (n + 3, 3)).astype(np.float32)),
                     opacity_logits=g.opacity_logits.at[:].set(rng.normal(size=n + 3).astype(np.float32)),
                     active=g.active.at[:].set(act))


def _inria_load_ply(path, max_sh_degree=3):
    """The reading part of INRIA 3DGS ``GaussianModel.load_ply`` (gaussian-splatting, scene/gaussian_model.py),
    with its assertion on the number of f_rest properties."""
    from plyfile import PlyData

    plydata = PlyData.read(path)
    el = plydata.elements[0]
    xyz = np.stack((np.asarray(el["x"]), np.asarray(el["y"]), np.asarray(el["z"])), axis=1)
    extra_f_names = sorted([p.name for p in el.properties if p.name.startswith("f_rest_")],
                           key=lambda x: int(x.split("_")[-1]))
    assert len(extra_f_names) == 3 * (max_sh_degree + 1) ** 2 - 3
    features_extra = np.zeros((xyz.shape[0], len(extra_f_names)))
    for idx, attr_name in enumerate(extra_f_names):
        features_extra[:, idx] = np.asarray(el[attr_name])
    features_extra = features_extra.reshape((features_extra.shape[0], 3, (max_sh_degree + 1) ** 2 - 1))
    scale_names = sorted([p.name for p in el.properties if p.name.startswith("scale_")], key=lambda x: int(x[6:]))
    rot_names = sorted([p.name for p in el.properties if p.name.startswith("rot")], key=lambda x: int(x[4:]))
    return xyz, features_extra, len(scale_names), len(rot_names), np.asarray(el["opacity"])


def test_inria_loader_accepts_our_ply(tmp_path):
    g = _map()
    p = str(tmp_path / "m.ply")
    assert io.save_ply(g, p) == 7
    xyz, rest, n_scale, n_rot, opac = _inria_load_ply(p)
    np.testing.assert_array_equal(xyz, np.asarray(g.means)[:7])
    assert rest.shape == (7, 3, 15) and not rest.any()
    assert n_scale == 3 and n_rot == 4
    np.testing.assert_array_equal(opac, np.asarray(g.opacity_logits)[:7])


@pytest.mark.parametrize("fmt", ["ascii", "binary_big_endian"])
def test_ascii_and_big_endian_ply_load_the_same_map(tmp_path, fmt):
    from plyfile import PlyData

    g = _map()
    p = str(tmp_path / "m.ply")
    io.save_ply(g, p)
    ply = PlyData.read(p)
    ply.text = fmt == "ascii"
    ply.byte_order = ">" if fmt == "binary_big_endian" else "="
    q = str(tmp_path / f"{fmt}.ply")
    ply.write(q)
    assert fmt.encode() in open(q, "rb").read(200)
    a, b = io.load_ply(p), io.load_ply(q)
    for k in ("means", "log_scales", "quats", "opacity_logits", "colors"):
        np.testing.assert_allclose(np.asarray(getattr(b, k)), np.asarray(getattr(a, k)), rtol=1e-6, atol=1e-7)


def test_sh_coefficients_are_read_channel_major(tmp_path):
    from plyfile import PlyData, PlyElement

    n, deg = 4, 1  # degree 1: 3 f_rest per channel, 9 in all
    rng = np.random.default_rng(2)
    rest = rng.normal(size=(n, 3, 3)).astype(np.float32)  # (N, channel, coefficient), INRIA's order
    props = [(k, "f4") for k in ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2")]
    props += [(f"f_rest_{i}", "f4") for i in range(9)]
    props += [(k, "f4") for k in ("opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")]
    v = np.zeros(n, dtype=props)
    for i in range(9):
        v[f"f_rest_{i}"] = rest.reshape(n, 9)[:, i]
    v["f_dc_0"] = 1.0
    v["rot_0"] = 1.0
    p = str(tmp_path / "sh1.ply")
    PlyData([PlyElement.describe(v, "vertex")]).write(p)
    a = io.read_ply_arrays(p)
    assert a["sh"].shape == (n, (deg + 1) ** 2, 3)
    np.testing.assert_allclose(a["sh"][:, 1:], rest.transpose(0, 2, 1))
    np.testing.assert_allclose(a["sh"][:, 0, 0], 1.0)
    assert io.load_ply(p).n_active == n
    from numpy.lib.recfunctions import repack_fields

    v2 = repack_fields(v[[name for name, _ in props if name != "f_rest_8"]])
    PlyData([PlyElement.describe(v2, "vertex")]).write(str(tmp_path / "bad.ply"))
    with pytest.raises(ValueError, match="f_rest"):
        io.load_ply(str(tmp_path / "bad.ply"))


def test_missing_ply_is_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.ply"):
        io.load_ply(str(tmp_path / "nope.ply"))
