"""Densification, the mapping loss, the GaussianMap pytree, tracking, save/load and the TUM loader."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from splatsearch import io
from splatsearch.gaussians import append, compact, empty_map, grow
from splatsearch.kernels.densify import densify
from splatsearch.mapper import Mapper, MapperConfig, perturb_viewmat, track

TUM = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "tum_fr1_xyz_first10")
K8 = np.array([[50.0, 0, 4.0], [0, 50.0, 3.0], [0, 0, 1]], np.float32)


def test_densify_mask_on_hand_made_depth():
    H, W = 6, 8
    d_obs = np.full((H, W), 2.0, np.float32)
    d_obs[0, :] = 0.0  # invalid row: never densified
    alpha = np.ones((H, W), np.float32)
    alpha[1, 1] = 0.2  # empty map here -> densify
    d_hat = np.full((H, W), 2.0, np.float32)
    d_hat[:, :] += np.linspace(-0.001, 0.001, W)[None]  # small errors set the median
    d_hat[3, 4] = 3.0  # map behind the observation, large error -> densify
    d_hat[4, 5] = 1.0  # map in front of the observation: not (D_obs < D_hat)
    out = densify(d_obs, alpha, d_hat, np.full((H, W, 3), 0.3, np.float32), np.eye(4), K8, tau_o=0.5, k=50)
    expect = np.zeros((H, W), bool)
    expect[1, 1] = expect[3, 4] = True
    np.testing.assert_array_equal(out["mask"], expect)
    assert out["means"].shape == (2, 3) and out["quats"].shape == (2, 4)
    # back-projection through the pixel centre, scale z / f, opacity 0.5, the pixel's colour
    np.testing.assert_allclose(out["means"][0], [(1.5 - 4) / 50 * 2, (1.5 - 3) / 50 * 2, 2.0], rtol=1e-6)
    np.testing.assert_allclose(np.exp(out["log_scales"]), 2.0 / 50, rtol=1e-5)
    np.testing.assert_allclose(out["colors"], 0.3)
    np.testing.assert_allclose(out["opacity_logits"], 0.0)
    # k and tau_o are parameters
    loose = densify(d_obs, alpha, d_hat, np.zeros((H, W, 3), np.float32), np.eye(4), K8, tau_o=0.1, k=1e6)
    assert not loose["mask"].any()


def test_densify_stride_and_pose():
    H, W = 6, 8
    d_obs = np.full((H, W), 1.0, np.float32)
    z = np.zeros((H, W), np.float32)
    vm = np.eye(4, dtype=np.float32)
    vm[:3, 3] = [0.5, 0.0, 0.0]  # world-to-camera: camera sits at x = -0.5
    out = densify(d_obs, z, z, np.zeros((H, W, 3), np.float32), vm, K8, stride=2)
    assert out["mask"].sum() == 12 and out["mask"][::2, ::2].all()
    np.testing.assert_allclose(out["means"][0], [(0.5 - 4) / 50 - 0.5, (0.5 - 3) / 50, 1.0], rtol=1e-5)
    with pytest.raises(ValueError, match="alpha"):
        densify(d_obs, z[:2], z, np.zeros((H, W, 3), np.float32), vm, K8)


def _axes(out):
    """World axes (n, 3, 3; columns) and scales (n, 3) of densified Gaussians."""
    from scipy.spatial.transform import Rotation

    q = out["quats"]
    R = Rotation.from_quat(np.concatenate([q[:, 1:], q[:, :1]], 1)).as_matrix()
    return R, np.exp(out["log_scales"])


def test_densify_surface_aligned_shapes():
    H, W = 24, 32
    K = np.array([[40.0, 0, 16.0], [0, 40.0, 12.0], [0, 0, 1]], np.float32)
    c2w = np.eye(4)
    c2w[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]  # a robot camera: forward = world x, down = world -z
    c2w[:3, 3] = [1.0, 2.0, 1.3]
    vm = np.linalg.inv(c2w).astype(np.float32)
    # a floor 1.3 m below the camera, seen at grazing angles in the lower half of the image
    rows = np.arange(H)[:, None] + 0.5 - K[1, 2]
    floor = np.where(rows > 0.5, 1.3 * K[1, 1] / np.maximum(rows, 1e-6), 0.0) * np.ones((1, W))
    floor = floor.astype(np.float32)
    z0 = np.zeros((H, W), np.float32)
    rgb = np.zeros((H, W, 3), np.float32)
    iso = densify(floor, z0, z0, rgb, vm, K, stride=2)
    out = densify(floor, z0, z0, rgb, vm, K, stride=2, surface_aligned=True)
    np.testing.assert_array_equal(out["mask"], iso["mask"])  # same Gaussians, same places
    np.testing.assert_allclose(out["means"], iso["means"])
    R, s = _axes(out)
    thin = R[np.arange(len(s)), :, np.argmin(s, 1)]
    assert np.all(np.abs(thin[:, 2]) > 0.99)  # the thin axis is the floor's normal (world z)
    # flat, and longer than the isotropic footprint along the floor away from the camera
    assert np.all(s.min(1) < 0.2 * s.max(1))
    assert np.median(s.max(1) / np.exp(iso["log_scales"][:, 0])) > 2.0
    assert np.all(s.max(1) <= 6.0 * np.exp(iso["log_scales"][:, 0]) * 1.0001)  # max_stretch
    # a wall facing the camera keeps the isotropic size in its plane
    wall = np.full((H, W), 2.0, np.float32)
    out = densify(wall, z0, z0, rgb, vm, K, stride=2, surface_aligned=True)
    R, s = _axes(out)
    s_iso = np.exp(densify(wall, z0, z0, rgb, vm, K, stride=2)["log_scales"])
    np.testing.assert_allclose(np.sort(s, 1)[:, 1:], s_iso[:, 1:], rtol=1e-4)
    thin = R[np.arange(len(s)), :, np.argmin(s, 1)]
    assert np.all(np.abs(thin @ c2w[:3, 2]) > 0.99)  # the normal looks back at the camera
    # at a depth edge the shape comes from the pixel's own side, not from the step across
    edge = wall.copy()
    edge[:, W // 2:] = 5.0
    _, s = _axes(densify(edge, z0, z0, rgb, vm, K, stride=2, surface_aligned=True))
    s_iso = np.exp(densify(edge, z0, z0, rgb, vm, K, stride=2)["log_scales"])
    np.testing.assert_allclose(s.max(1), s_iso[:, 0], rtol=1e-4)
    with pytest.raises(ValueError, match="max_stretch"):
        densify(wall, z0, z0, rgb, vm, K, stride=2, surface_aligned=True, max_stretch=0.0)


def _small_frames(n=3, w=64, h=48):
    from splatsearch.datasets import sim_trajectory

    frames, K, W, H, _ = sim_trajectory(1, n, w, h)
    return frames, K, W, H


def test_loss_falls_on_a_small_scene():
    frames, K, W, H = _small_frames(1)
    m = Mapper(K, W, H, MapperConfig(iters=1, stride=2, initial_capacity=256))
    f = frames[0]
    m.update(f.rgb, f.depth, f.viewmat)
    first = m.last_loss
    m.cfg.iters = 60  # the jitted step does not depend on the iteration count
    m.update(f.rgb, f.depth, f.viewmat)  # the same view again: (almost) pure optimisation
    assert m.last_loss < 0.5 * first, (first, m.last_loss)
    ev = m.evaluate([f])
    assert ev["psnr"] > 18 and ev["depth_l1"] < 0.1


def test_capacity_growth_keeps_optimiser_state_consistent():
    g = empty_map(4)
    tx = optax.adam(0.1)
    rng = np.random.default_rng(0)

    def new(n):
        return {"means": rng.normal(size=(n, 3)), "log_scales": np.full((n, 3), -2.0), "quats": np.tile([1, 0, 0, 0.0], (n, 1)),
                "opacity_logits": np.zeros(n), "colors": rng.uniform(size=(n, 3))}

    st = tx.init(g.params())
    g, st, idx = append(g, st, new(3))
    np.testing.assert_array_equal(idx, [0, 1, 2])
    grads = jax.tree_util.tree_map(jnp.ones_like, g.params())
    _, st = tx.update(grads, st, g.params())
    mu_before = np.asarray(st[0].mu["means"])[:3].copy()
    g, st, idx = append(g, st, new(10))  # 13 > 4: capacity doubles to 16
    assert g.capacity == 16 and g.n_active == 13
    np.testing.assert_array_equal(idx, np.arange(3, 13))
    for leaf_p, leaf_m in zip(jax.tree_util.tree_leaves(g.params()), jax.tree_util.tree_leaves(st[0].mu)):
        assert leaf_p.shape == leaf_m.shape
    np.testing.assert_array_equal(np.asarray(st[0].mu["means"])[:3], mu_before)
    assert not np.asarray(st[0].mu["means"])[3:].any() and not np.asarray(st[0].nu["colors"])[3:].any()
    # the padded state still works with the optimiser
    upd, st = tx.update(jax.tree_util.tree_map(jnp.ones_like, g.params()), st, g.params())
    assert np.isfinite(np.asarray(upd["means"])).all()
    # compaction moves parameters and moments together
    keep = np.zeros(16, bool)
    keep[[1, 5, 7]] = True
    means_kept = np.asarray(g.means)[[1, 5, 7]]
    mu_kept = np.asarray(st[0].mu["means"])[[1, 5, 7]]
    g2, st2 = compact(g, st, keep)
    assert g2.capacity == 16 and g2.n_active == 3
    np.testing.assert_array_equal(np.asarray(g2.means)[:3], means_kept)
    np.testing.assert_array_equal(np.asarray(st2[0].mu["means"])[:3], mu_kept)
    assert not np.asarray(st2[0].mu["means"])[3:].any()
    g3, _ = grow(g2, None, 10)
    assert g3.capacity == 16  # already large enough


def test_jitted_step_compiles_once_per_capacity_bucket():
    frames, K, W, H = _small_frames(3)
    cfg = MapperConfig(iters=2, stride=4, initial_capacity=4096)
    m = Mapper(K, W, H, cfg)
    before = m._step._cache_size()
    for f in frames:
        m.update(f.rgb, f.depth, f.viewmat)
    assert m.map.capacity == 4096
    after = m._step._cache_size()
    # submaps come in power-of-two capacities: 1024, 2048 or the full 4096 at most (fewer when
    # an earlier test with the same camera already compiled some of them: the cache is shared)
    assert after >= 1 and after - before <= 3
    # a second mapper with the same camera and loss shares the compiled step
    m2 = Mapper(K, W, H, cfg)
    for f in frames:
        m2.update(f.rgb, f.depth, f.viewmat)
    assert m2._step is m._step and m2._step._cache_size() == after


def test_submap_optimises_like_the_whole_map():
    frames, K, W, H = _small_frames(3)
    res = {}
    for sub in (False, True):
        m = Mapper(K, W, H, MapperConfig(iters=6, stride=2, initial_capacity=8192, submap=sub))
        for f in frames:
            m.update(f.rgb, f.depth, f.viewmat)
        res[sub] = m.evaluate(frames)
    # the same frames, the same seeds: a submap only leaves out Gaussians no frame sees
    assert abs(res[True]["psnr"] - res[False]["psnr"]) < 0.5
    assert abs(res[True]["depth_l1"] - res[False]["depth_l1"]) < 0.01


def _visible_rows_reference(m, viewmats):
    """The submap's rows as stop 46's code found them: every view tested on every row."""
    n = m.map.n_active
    means = np.asarray(m.map.means)[:n]
    vis = np.zeros(n, bool)
    mg, K = m.cfg.submap_margin, m.K
    for vm in viewmats:
        vm = np.asarray(vm, np.float32)
        pc = means @ vm[:3, :3].T + vm[:3, 3]
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K[0, 0] * pc[:, 0] / z + K[0, 2]
            v = K[1, 1] * pc[:, 1] / z + K[1, 2]
        vis |= (z > 0.01) & (u > -mg * m.W) & (u < (1 + mg) * m.W) & (v > -mg * m.H) & (v < (1 + mg) * m.H)
    rows = np.nonzero(vis)[0]
    return None if len(rows) == 0 or max(1024, 1 << int(np.ceil(np.log2(len(rows))))) >= m.map.capacity else rows


def test_visible_rows_equal_the_all_rows_test():
    """Testing only the rows no earlier view saw, and stopping once the whole map is the answer,
    finds exactly what testing every row in every view finds (issue 23, stop 47)."""
    rng = np.random.default_rng(3)
    K = np.array([[100.0, 0, 64], [0, 100.0, 48], [0, 0, 1]], np.float32)
    m = Mapper(K, 128, 96, MapperConfig(initial_capacity=4096))
    seen = set()
    for n_pts, spread in ((3000, 0.3), (3000, 20.0), (5000, 60.0)):
        new = densify(np.full((96, 128), 2.0, np.float32), np.zeros((96, 128), np.float32),
                      np.zeros((96, 128), np.float32), rng.random((96, 128, 3)).astype(np.float32),
                      np.eye(4, dtype=np.float32), K, stride=1)
        new.pop("mask")
        k = min(n_pts, len(new["means"]))
        new = {key: v[:k] for key, v in new.items()}
        new["means"] = (rng.normal(size=(k, 3)) * spread + [0.0, 0.0, 3.0]).astype(np.float32)
        m.map, m.opt_state, _ = append(m.map, m.opt_state, new)
        for _ in range(5):
            views = [perturb_viewmat(np.eye(4, dtype=np.float32), rng.normal(size=6).astype(np.float32) * 0.3)
                     for _ in range(int(rng.integers(1, 6)))]
            got, ref = m._visible_rows(views), _visible_rows_reference(m, views)
            assert (got is None) == (ref is None)
            if ref is not None:
                np.testing.assert_array_equal(got, ref)
            seen.add(ref is None)
    assert seen == {True, False}  # both answers came up: the whole map, and a submap


def _map_with_content():
    frames, K, W, H = _small_frames(1)
    m = Mapper(K, W, H, MapperConfig(iters=3, stride=2, initial_capacity=256))
    m.update(frames[0].rgb, frames[0].depth, frames[0].viewmat)
    return m, frames[0]


def test_save_load_round_trip_is_exact(tmp_path):
    m, f = _map_with_content()
    p_ply, p_npz = str(tmp_path / "m.ply"), str(tmp_path / "m.npz")
    n = io.save_ply(m.map, p_ply)
    assert n == m.map.n_active
    g = io.load_ply(p_ply)
    act = np.asarray(m.map.active)
    for k in ("means", "log_scales", "opacity_logits"):
        np.testing.assert_array_equal(np.asarray(getattr(g, k))[:n], np.asarray(getattr(m.map, k))[act])
    q = np.asarray(m.map.quats)[act]
    np.testing.assert_allclose(np.asarray(g.quats)[:n], q / np.linalg.norm(q, axis=1, keepdims=True), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(g.colors)[:n], np.clip(np.asarray(m.map.colors)[act], 0, 1), atol=1e-6)
    io.save_npz(m.map, p_npz, K=m.K)
    g2, extra = io.load_npz(p_npz)
    for k in ("means", "log_scales", "quats", "opacity_logits", "colors", "active"):
        np.testing.assert_array_equal(np.asarray(getattr(g2, k)), np.asarray(getattr(m.map, k)))
    np.testing.assert_array_equal(extra["K"], m.K)
    # rendering the reloaded maps gives the same image
    from splatsearch.mapper import render_map

    a = render_map(m.map, f.viewmat, m.K, m.W, m.H)[0]
    b = render_map(g, f.viewmat, m.K, m.W, m.H)[0]
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-5)


def test_ply_header_is_inria_layout(tmp_path):
    m, _ = _map_with_content()
    p = str(tmp_path / "m.ply")
    io.save_ply(m.map, p)
    head = open(p, "rb").read(4000).split(b"end_header")[0].decode()
    props = [line.split()[-1] for line in head.splitlines() if line.startswith("property")]
    assert props == list(io.PLY_PROPS)
    assert "format binary_little_endian 1.0" in head


def test_corrupt_files_are_rejected(tmp_path):
    m, _ = _map_with_content()
    p = tmp_path / "m.ply"
    io.save_ply(m.map, str(p))
    data = p.read_bytes()
    (tmp_path / "trunc.ply").write_bytes(data[: len(data) - 100])
    with pytest.raises(ValueError, match="truncated"):
        io.load_ply(str(tmp_path / "trunc.ply"))
    (tmp_path / "magic.ply").write_bytes(b"xyz" + data[3:])
    with pytest.raises(ValueError, match="not a PLY"):
        io.load_ply(str(tmp_path / "magic.ply"))
    (tmp_path / "noprop.ply").write_bytes(data.replace(b"property float opacity\n", b""))
    with pytest.raises(ValueError, match="opacity"):
        io.load_ply(str(tmp_path / "noprop.ply"))
    (tmp_path / "ascii.ply").write_bytes(data.replace(b"binary_little_endian", b"ascii"))  # binary body
    with pytest.raises(ValueError, match="malformed"):
        io.load_ply(str(tmp_path / "ascii.ply"))
    q = tmp_path / "m.npz"
    io.save_npz(m.map, str(q))
    raw = q.read_bytes()
    (tmp_path / "trunc.npz").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ValueError):
        io.load_npz(str(tmp_path / "trunc.npz"))
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(ValueError, match="not a splatsearch"):
        io.load_npz(str(tmp_path / "other.npz"))


def test_save_is_atomic_on_failure(tmp_path, monkeypatch):
    m, _ = _map_with_content()
    p = tmp_path / "m.ply"
    io.save_ply(m.map, str(p))
    before = p.read_bytes()

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError):
        io.save_ply(m.map, str(p))
    assert p.read_bytes() == before  # the old file is untouched
    assert [x.name for x in tmp_path.iterdir()] == ["m.ply"]  # no temp file left behind


def test_tracking_reduces_pose_error():
    frames, K, W, H = _small_frames(1, 96, 72)
    f = frames[0]
    m = Mapper(K, W, H, MapperConfig(iters=20, stride=1, initial_capacity=8192))
    for _ in range(3):
        m.update(f.rgb, f.depth, f.viewmat)
    xi = jnp.array([0.01, -0.015, 0.01, 0.03, -0.02, 0.02])
    noisy = np.asarray(perturb_viewmat(jnp.asarray(f.viewmat), xi))
    refined, _ = track(m.map, f.rgb, f.depth, noisy, m.K, W, H, iters=80, lr=2e-3)
    err = lambda vm: np.linalg.norm(np.linalg.inv(vm)[:3, 3] - np.linalg.inv(f.viewmat)[:3, 3])  # noqa: E731
    assert err(refined) < 0.5 * err(noisy), (err(noisy), err(refined))


def test_overlap_window_picks_keyframes_that_see_the_frame():
    from splatsearch.mapper import Frame
    from splatsearch.sim.env import camera_viewmat, intrinsics

    K = intrinsics(64, 48)
    m = Mapper(K, 64, 48, MapperConfig(window=3, iters=0, initial_capacity=16))
    depth = np.full((48, 64), 2.0, np.float32)
    rgb = np.zeros((48, 64, 3), np.float32)
    # keyframes 0 and 2 look along +x like the new frame; 1 and 3 look the other way
    yaws = [0.0, np.pi, 0.1, np.pi]
    m.keyframes = [Frame(rgb, depth, camera_viewmat(0, 0, y)) for y in yaws]
    cur = Frame(rgb, depth, camera_viewmat(0.2, 0, 0.05))
    chosen = m._select_window(cur)
    # the latest keyframe always joins; the other slot goes to the best-overlapping one
    assert [id(f) for f in chosen] == [id(m.keyframes[2]), id(m.keyframes[3])]
    m.cfg.window_select = "recent"
    assert [id(f) for f in m._select_window(cur)] == [id(m.keyframes[2]), id(m.keyframes[3])]
    m.cfg.window = 4
    m.cfg.window_select = "overlap"
    assert [id(f) for f in m._select_window(cur)] == [id(m.keyframes[i]) for i in (0, 2, 3)]
    with pytest.raises(ValueError, match="window_select"):
        MapperConfig(window_select="nearest").validate()


def test_bad_input_to_mapper():
    with pytest.raises(ValueError):
        Mapper(K8, 8, 6, MapperConfig(iters=-1))
    m = Mapper(K8, 8, 6, MapperConfig(iters=1, initial_capacity=16))
    with pytest.raises(ValueError, match="expected"):
        m.update(np.zeros((6, 8, 3)), np.zeros((5, 8)), np.eye(4))
    d = np.ones((6, 8))
    d[0, 0] = np.nan
    with pytest.raises(ValueError, match="depth"):
        m.update(np.zeros((6, 8, 3)), d, np.eye(4))


@pytest.mark.skipif(not os.path.isdir(TUM), reason="shared TUM frames not present")
def test_tum_loader_and_mapping_real_frames():
    from splatsearch.datasets import load_tum

    seq = load_tum(TUM, undistort=False)
    frames, K, W, H = seq.frames, seq.K, seq.width, seq.height
    assert len(frames) == 10 and (W, H) == (640, 480)
    np.testing.assert_allclose(K[0, 0], 517.3)
    d = frames[0].depth
    assert 0.3 < np.median(d[d > 0]) < 3.0 and (d == 0).any()  # real sensor: holes
    # consecutive 30 Hz poses move by millimetres to centimetres
    c = [np.linalg.inv(f.viewmat)[:3, 3] for f in frames]
    steps = np.linalg.norm(np.diff(c, axis=0), axis=1)
    assert (steps < 0.05).all() and steps.sum() > 0.005
    m = Mapper(K, W, H, MapperConfig(iters=15, stride=2, initial_capacity=1 << 17))
    for f in frames[:2]:
        m.update(f.rgb, f.depth, f.viewmat)
    ev = m.evaluate(frames[:2])
    assert ev["psnr"] > 12 and ev["depth_l1"] < 0.12, ev  # 2 frames only: a sanity bound, not a quality target
