"""VCICN: the view-completion model, its training, its weights and its training data."""

from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest

from splatsearch.search.completion import (
    VCICNConfig,
    VCICNInpainter,
    WeightsError,
    build_model,
    init_params,
    load_weights,
    prepare_views,
    relative_cameras,
    save_weights,
    shipped_weights,
    shipped_weights_available,
)

TINY = VCICNConfig(width=16, height=16, features=8, heads=2, blocks=1)
FIXTURE = os.path.join(os.path.dirname(__file__), "data", "vcicn_val_fixture.npz")


@pytest.fixture(scope="module")
def tiny_params():
    """The untrained TINY model's parameters (seed 0), built once for the module: every
    ``init_params`` call jits a fresh ``model.init`` and compiles it again (about 10 s on 2 cores)."""
    return init_params(TINY)


@pytest.fixture(scope="module")
def tiny_weights(tmp_path_factory, tiny_params) -> str:
    """A weights file of the untrained TINY model, built once for the inpainter tests."""
    p = str(tmp_path_factory.mktemp("vcicn") / "w.npz")
    save_weights(p, tiny_params, TINY)
    return p


_APPLY = {}


def _apply(cfg, params, x, cams=None, valid=None):
    import jax

    if cfg not in _APPLY:  # one compiled program per shape instead of eager op-by-op calls
        _APPLY[cfg] = jax.jit(build_model(cfg).apply)
    B, V = x.shape[:2]
    cams = np.zeros((B, V, 13), np.float32) if cams is None else cams
    valid = np.ones((B, V), bool) if valid is None else valid
    return np.asarray(_APPLY[cfg](params, x, cams, valid))


def test_model_shapes_and_range(tiny_params):
    x = np.random.default_rng(0).random((2, 3, 16, 16, 4)).astype(np.float32)
    out = _apply(TINY, tiny_params, x)
    assert out.shape == (2, 3, 16, 16, 3)
    assert np.all((out >= 0) & (out <= 1))


def test_views_exchange_information_and_padding_is_ignored(tiny_params):
    params = tiny_params
    rng = np.random.default_rng(1)
    # batch 2 (only sample 0 is checked) so that the apply compiled for the shapes test is reused
    x = rng.random((2, 3, 16, 16, 4)).astype(np.float32)
    base = _apply(TINY, params, x)
    y = x.copy()
    y[0, 2] = rng.random((16, 16, 4))  # change view 2 only
    changed = _apply(TINY, params, y)
    assert np.abs(changed[0, 0] - base[0, 0]).max() > 1e-4  # view 0 sees view 2 through attention
    # a padded (invalid) view must not influence the valid ones
    valid = np.array([[True, True, False]] * 2)
    a = _apply(TINY, params, x, valid=valid)
    b = _apply(TINY, params, y, valid=valid)
    np.testing.assert_allclose(a[0, :2], b[0, :2], atol=1e-5)


def test_prepare_views_and_cameras():
    img = np.full((2, 32, 32, 3), 0.8, np.float32)
    img[:, :, :16] = 0.0  # the hole is black in the render
    holes = np.zeros((2, 32, 32), bool)
    holes[:, :, :16] = True
    x, hole = prepare_views(img, holes, 16, 16)
    assert x.shape == (2, 16, 16, 4) and hole.shape == (2, 16, 16)
    assert np.all(hole[:, :, :8] == 1) and np.all(hole[:, :, 8:] == 0)
    np.testing.assert_allclose(x[:, :, 8:, :3], 0.8, atol=1e-6)  # no hole colour leaks into known pixels
    vms = np.stack([np.eye(4), np.eye(4)])
    vms[1, :3, 3] = [0.5, 0, 0]
    c = relative_cameras(vms, 2)
    np.testing.assert_allclose(c[0, :9], np.eye(3).ravel())
    np.testing.assert_allclose(c[1, 9:12], [0.5, 0, 0])
    assert np.all(relative_cameras(None, 2) == 0)


def _synthetic_shards(d, seeds, views=4, size=24):
    """Shards in the generator's format: smooth images, renders = ground truth with holes."""
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:size, 0:size] / size
    for s in seeds:
        O = 3
        gt = np.zeros((O, views, size, size, 3), np.uint8)
        for o in range(O):
            for v in range(views):
                c = rng.random((3, 3))
                img = c[0] + np.outer(yy.ravel(), c[1]).reshape(size, size, 3) + np.outer(xx.ravel(), c[2]).reshape(size, size, 3)
                gt[o, v] = (np.clip(img / 2.5, 0, 1) * 255).astype(np.uint8)
        alpha = np.full((O, views, size, size), 255, np.uint8)
        for o in range(O):
            for v in range(views):
                r, c = rng.integers(0, size - 10, 2)
                alpha[o, v, r:r + 10, c:c + 10] = 0
        render = np.where(alpha[..., None] > 0, gt, 0).astype(np.uint8)
        vms = np.tile(np.eye(4, dtype=np.float32), (O, views, 1, 1))
        vms[..., 0, 3] = rng.normal(0, 1, (O, views))
        np.savez(os.path.join(d, f"house_{s:04d}.npz"), render=render, alpha=alpha, gt=gt, viewmats=vms,
                 valid=np.ones((O, views), bool), render_depth=np.zeros((O, views, size, size), np.float16),
                 gt_depth=np.zeros((O, views, size, size), np.float16))


@pytest.mark.slow  # compiles the training step twice (fresh and resumed run), about 55 s on 2 cores
def test_tiny_training_lowers_validation_loss_and_resumes(tmp_path):
    from splatsearch.vcicn.train import TrainConfig, train

    data = tmp_path / "data"
    data.mkdir()
    _synthetic_shards(str(data), [0, 1, 2, 9])
    out = str(tmp_path / "run")
    cfg = TrainConfig(steps=30, batch=2, lr=3e-3, width=16, height=16, features=8, eval_every=10, patience=50)
    r = train(str(data), out, cfg, fresh=True, progress=False)
    log = json.load(open(os.path.join(out, "log.json")))
    assert r["steps"] == 30 and len(log) == 3
    assert log[-1]["loss"] < log[0]["loss"]
    assert r["val_houses"] == [9] and r["train_houses"] == [0, 1, 2]
    # resume: a longer run continues from the checkpoint's step instead of starting over
    r2 = train(str(data), out, TrainConfig(**{**cfg.__dict__, "steps": 40}), progress=False,
               export=str(tmp_path / "w.npz"), command="test")
    log2 = json.load(open(os.path.join(out, "log.json")))
    assert r2["steps"] == 40 and len(log2) == 4 and log2[:3] == log
    prov = json.load(open(tmp_path / "w.json"))
    assert prov["val_houses"] == [9] and prov["sha256"] == r2["export_sha256"] and prov["command"] == "test"
    VCICNInpainter(str(tmp_path / "w.npz"))  # the exported file loads with its provenance check


def test_bad_grad_loss_is_refused(tmp_path, capsys):
    """A negative or non-finite --grad-loss is refused by the parser with a clear message."""
    from splatsearch.cli import main

    for bad in ("-1", "nan"):
        with pytest.raises(SystemExit) as e:
            main(["vcicn", "train", "--data", str(tmp_path), "--out", str(tmp_path / "r2"), "--grad-loss", bad])
        assert e.value.code == 2
        assert "--grad-loss" in capsys.readouterr().err


@pytest.mark.slow  # compiles a second training step (about 25 s on 2 cores)
def test_one_step_training_runs(tmp_path):
    """A 1-step run still has a learning-rate schedule (the warm-up is shorter than the run)."""
    from splatsearch.vcicn.train import TrainConfig, train

    data = tmp_path / "data"
    data.mkdir()
    _synthetic_shards(str(data), [0, 9])
    cfg = TrainConfig(steps=1, batch=1, width=16, height=16, features=8, eval_every=1)
    assert train(str(data), str(tmp_path / "run"), cfg, fresh=True, progress=False)["steps"] == 1


@pytest.mark.slow  # compiles the model at a second resolution (about 25 s on 2 cores)
def test_warm_start_across_resolutions(tmp_path):
    """Weights of one resolution start a run at another: the convolutions are copied, the
    bottleneck's position embedding is resized; another U-Net width is refused."""
    from splatsearch.search.completion import _flatten
    from splatsearch.vcicn.train import warm_start

    small = VCICNConfig(width=16, height=16, features=8, heads=2, blocks=1)
    big = VCICNConfig(width=32, height=24, features=8, heads=2, blocks=1)
    p = str(tmp_path / "small.npz")
    save_weights(p, init_params(small, seed=4), small)
    src = _flatten(load_weights(p)[0])
    started = warm_start(init_params(big, seed=5), p, big)
    got = _flatten(started)
    assert set(got) == set(src)
    for k, w in got.items():
        if k.endswith("/pos"):
            assert w.shape == (4 * 3, src[k].shape[1])  # (32/8 x 24/8 tokens, D)
            np.testing.assert_allclose(w.mean(0), src[k].mean(0), atol=0.02)
        else:
            np.testing.assert_array_equal(w, src[k])
    out = _apply(big, started, np.zeros((1, 2, 24, 32, 4), np.float32))
    assert out.shape == (1, 2, 24, 32, 3)
    with pytest.raises(ValueError, match="architecture"):
        warm_start({}, p, VCICNConfig(width=16, height=16, features=16, heads=2, blocks=1))


def test_gradient_loss_term():
    """The gradient term of the loss is zero for a perfect completion and grows with a blurred one."""
    import jax

    from splatsearch.search.completion import loss_fn

    rng = np.random.default_rng(0)
    gt = rng.random((1, 2, 16, 16, 3)).astype(np.float32)
    x = np.concatenate([np.zeros_like(gt), np.ones_like(gt[..., :1])], -1)  # everything is a hole
    hole, valid = np.ones((1, 2, 16, 16), np.float32), np.ones((1, 2), bool)
    blur = np.broadcast_to(gt.mean((2, 3), keepdims=True), gt.shape)
    extra = lambda pred: float(loss_fn(pred, x, hole, gt, valid, 1.0) - loss_fn(pred, x, hole, gt, valid))  # noqa: E731
    assert extra(gt) == pytest.approx(0.0, abs=1e-6)
    assert extra(blur) > 0.1
    assert jax.numpy.isfinite(loss_fn(blur, x, hole, gt, valid, 0.5))


def test_weights_round_trip_and_corruption(tmp_path, tiny_params):
    import jax

    params = tiny_params
    p = str(tmp_path / "w.npz")
    digest = save_weights(p, params, TINY, meta={"step": 7}, provenance={"note": "test"})
    back, cfg, meta = load_weights(p)
    assert cfg == TINY and meta == {"step": 7}
    for a, b in zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(back)):
        np.testing.assert_array_equal(np.asarray(a), b)
    assert json.load(open(tmp_path / "w.json"))["sha256"] == digest
    data = open(p, "rb").read()
    # truncated, without a provenance file: the archive itself is refused
    t = str(tmp_path / "t.npz")
    open(t, "wb").write(data[: len(data) // 2])
    with pytest.raises(WeightsError, match="corrupt or truncated"):
        load_weights(t)
    # one flipped byte against the provenance checksum
    bad = bytearray(data)
    bad[len(bad) // 3] ^= 0xFF
    open(p, "wb").write(bytes(bad))
    with pytest.raises(WeightsError, match="checksum"):
        load_weights(p)
    with pytest.raises(WeightsError, match="checksum"):
        VCICNInpainter(p)
    with pytest.raises(FileNotFoundError):
        load_weights(str(tmp_path / "missing.npz"))


def test_inpainter_keeps_known_pixels_and_runs_without_cameras(tiny_weights):
    p = tiny_weights
    inp = VCICNInpainter(p)
    rng = np.random.default_rng(0)
    img = rng.random((3, 30, 40, 3)).astype(np.float32)
    m = np.zeros((3, 30, 40), bool)
    m[0, 5:15, 5:20] = True
    out = inp.inpaint(img, m)
    assert out.shape == img.shape and out.dtype == np.float32
    np.testing.assert_array_equal(out[~m], img[~m])
    assert not np.allclose(out[m], img[m])
    vms = np.tile(np.eye(4), (3, 1, 1))
    out2 = inp.inpaint(img, m, viewmats=vms)
    np.testing.assert_array_equal(out2[~m], img[~m])
    with pytest.raises(ValueError):
        inp.inpaint(img, m[:, :-1])


def test_over_composite_fills_soft_pixels_and_keeps_opaque_ones(tiny_weights):
    from splatsearch.plugins import make_inpainter

    p = tiny_weights
    rng = np.random.default_rng(1)
    alpha = np.ones((2, 24, 32), np.float32)
    alpha[:, 4:10, 4:12] = 0.2  # holes
    alpha[:, 12:16, 4:12] = 0.7  # soft covered pixels
    img = (rng.random((2, 24, 32, 3)) * alpha[..., None]).astype(np.float32)  # composited over black
    m = alpha < 0.5
    holes_out = VCICNInpainter(p).inpaint(img, m)
    over = make_inpainter(f"vcicn:{p},composite=over")
    assert over.composite == "over"
    out = over.inpaint(img, m, alpha=alpha)
    opaque = alpha == 1.0
    np.testing.assert_array_equal(out[opaque], img[opaque])
    np.testing.assert_allclose(out[m], holes_out[m], atol=1e-6)
    soft = (alpha == 0.7)
    assert np.all(out[soft] >= img[soft]) and np.any(out[soft] > img[soft] + 0.05)
    import cv2

    pred = np.stack([cv2.resize(v, (32, 24), interpolation=cv2.INTER_LINEAR) for v in over.predict(img, m)])
    np.testing.assert_allclose(out[soft], np.clip(img[soft] + 0.3 * np.clip(pred[soft], 0, 1), 0, 1), atol=1e-5)
    # without the renders' opacity, "over" completes the holes only
    np.testing.assert_array_equal(over.inpaint(img, m), holes_out)
    with pytest.raises(ValueError, match="composite"):
        VCICNInpainter(p, composite="blend")


def test_nvsm_passes_opacity_so_over_composite_runs_in_the_agent(tiny_weights, random_blob_map):
    from splatsearch import sim
    from splatsearch.search.novel_views import hemisphere_viewpoints
    from splatsearch.search.object_search import verify_object

    p = tiny_weights
    rng = np.random.default_rng(0)
    gmap = random_blob_map(opacity=0.6)
    K = sim.intrinsics(64, 48)
    vms = hemisphere_viewpoints([0.0, 0.0, 0.0], 1.0, 3, (30.0,), min_height=None, max_height=None)[:2]
    goal = rng.uniform(0, 1, (48, 64, 3)).astype(np.float32)
    over = VCICNInpainter(p, composite="over")
    seen = {}
    inpaint = over.inpaint

    def spy(images, masks, viewmats=None, alpha=None):
        seen["alpha"] = alpha
        return inpaint(images, masks, viewmats=viewmats, alpha=alpha)

    over.inpaint = spy
    res = verify_object(goal, gmap, [0.0, 0.0, 0.0], K, 64, 48, inpainter=over, viewmats=vms)
    alpha = seen["alpha"]
    assert alpha is not None and alpha.shape == (2, 48, 64)
    soft = ~res.holes & (alpha < 0.999)
    opaque = alpha >= 1.0
    assert soft.any() and res.holes.any()
    # the soft covered pixels get the prediction behind them, the opaque ones stay as rendered
    assert np.all(res.images[soft] >= res.rendered[soft] - 1e-6)
    assert not np.allclose(res.images[soft], res.rendered[soft])
    np.testing.assert_array_equal(res.images[opaque], res.rendered[opaque])


def test_plugin_specs_and_variants(tiny_weights):
    from splatsearch.agent import AgentConfig
    from splatsearch.agent.config import resolve_variant
    from splatsearch.plugins import make_inpainter, resolve_inpainter_spec
    from splatsearch.search.inpainting import OpenCVInpainter

    p = tiny_weights
    assert isinstance(make_inpainter(f"vcicn:{p}"), VCICNInpainter)
    assert isinstance(make_inpainter("opencv"), OpenCVInpainter)
    with pytest.raises(FileNotFoundError):
        make_inpainter("vcicn:/nonexistent/w.npz")
    expected = "vcicn" if shipped_weights_available() else "opencv"
    assert resolve_inpainter_spec("auto") == expected
    assert resolve_variant(AgentConfig()).inpainter == expected
    assert resolve_variant(AgentConfig(variant="opencv_inpaint")).inpainter == "opencv"
    nv = resolve_variant(AgentConfig(variant="no_vcicn"))
    assert not nv.inpaint and nv.inpainter is None and nv.match_observations
    assert AgentConfig(variant="no_inpaint").variant == "no_vcicn"  # the earlier name is an alias


@pytest.mark.skipif(not shipped_weights_available(), reason="this installation ships no VCICN weights")
def test_shipped_weights_load_as_package_data():
    from importlib import resources

    params, cfg, meta, prov = shipped_weights()
    res = resources.files("splatsearch.weights").joinpath("vcicn.npz")
    assert res.is_file() and prov["sha256"] and max(prov["val_houses"]) < 1000
    assert os.path.getsize(str(res)) <= 20 * 1024 * 1024
    # package data, so an installed wheel carries it
    import tomllib

    root = os.path.dirname(os.path.dirname(__file__))
    with open(os.path.join(root, "pyproject.toml"), "rb") as f:
        py = tomllib.load(f)
    assert "splatsearch.weights" in py["tool"]["setuptools"]["packages"]
    assert {"*.npz", "*.json"} <= set(py["tool"]["setuptools"]["package-data"]["splatsearch.weights"])


@pytest.mark.skipif(not (shipped_weights_available() and os.path.exists(FIXTURE)),
                    reason="needs the shipped weights and the held-apart fixture")
def test_completion_of_held_apart_views_is_closer_to_ground_truth():
    from splatsearch.vcicn.train import psnr

    z = np.load(FIXTURE)
    render, alpha, gt, vms = z["render"] / 255.0, z["alpha"], z["gt"] / 255.0, z["viewmats"]
    holes = alpha < 128
    out = VCICNInpainter().inpaint(render.astype(np.float32), holes, viewmats=vms)
    assert psnr(out, gt, holes) > psnr(render, gt, holes) + 3.0
    assert psnr(out, gt) > psnr(render, gt)


@pytest.fixture(scope="module")
def small_shard():
    from splatsearch.vcicn.data import DataConfig, house_shard

    cfg = DataConfig(width=64, height=48, store_scale=1, n_views=4, goal_views=1, max_objects=1, min_obs=1,
                     max_obs=2, obs_min_px=30, view_min_px=10)
    return cfg, house_shard(3, False, cfg)


def test_data_shard_pairs_share_cameras(small_shard):
    from splatsearch import sim

    cfg, a = small_shard
    assert a["render"].shape[1:] == (cfg.views_per_object, 48, 64, 3) and len(a["render"]) == 1
    assert a["valid"][0].sum() >= 2
    house = sim.make_house(3)
    r = sim.HouseRenderer(house)
    for v in np.flatnonzero(a["valid"][0]):
        f = r.render(a["viewmats"][0, v], a["K"], 64, 48, max_depth=5.0)
        np.testing.assert_array_equal(a["gt"][0, v], (np.clip(f.rgb, 0, 1) * 255 + 0.5).astype(np.uint8))
        np.testing.assert_allclose(a["gt_depth"][0, v], f.depth, atol=1e-2)
        # the render sees the same scene from the same camera: where it is opaque, its depth
        # follows the ray caster's (loosely: a 64 x 48 local map is coarse; at the default
        # 320 x 240 the median error is a few millimetres)
        ok = (a["alpha"][0, v] > 200) & (f.depth > 0)
        if ok.sum() > 50:
            err = np.abs(a["render_depth"][0, v][ok].astype(np.float32) - f.depth[ok])
            assert np.median(err) < 0.4


def test_data_shard_is_deterministic(small_shard):
    from splatsearch.vcicn.data import house_shard

    cfg, a = small_shard
    b = house_shard(3, False, cfg)
    assert set(a) == set(b)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_parse_houses_refuses_evaluation_seeds(tmp_path):
    from splatsearch.vcicn.data import generate, parse_houses

    assert parse_houses("0-3,7") == [0, 1, 2, 3, 7]
    with pytest.raises(ValueError, match="0-499"):
        parse_houses("995-1002")
    with pytest.raises(ValueError):
        generate([1000], str(tmp_path))
