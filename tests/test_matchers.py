"""The matchers studied for the NVSM (issue 23), the separation measure and the NVSM-view dumper."""

import dataclasses
import json
import os
import sys

import numpy as np
import pytest

from splatsearch import sim
from splatsearch.plugins import make_matcher
from splatsearch.search.matching import (
    RENDER_TAU_M,
    LocalFeatureMatcher,
    Matcher,
    SIFTMatcher,
    gms_filter,
    roc_auc,
    rootsift,
)

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))

W, H = 320, 240


def _has_akaze() -> bool:
    import cv2

    return hasattr(cv2, "AKAZE_create") or hasattr(getattr(cv2, "xfeatures2d", None), "AKAZE_create")


@pytest.fixture(scope="module")
def env():
    # one model per furniture class: instances differ only in where they stand and what is around them
    return sim.HouseEnv(sim.make_house(0, identical_furniture=True), width=W, height=H)


def _view(env, obj, az_deg, dist):
    az = np.radians(az_deg)
    eye = np.array([obj.center[0] + dist * np.cos(az), obj.center[1] + dist * np.sin(az), sim.env.CAMERA_HEIGHT])
    return env.render_view(sim.look_at_viewmat(eye, obj.center)).rgb


def _open_side(env, obj) -> float:
    """Azimuth (degrees) of the 24 around ``obj`` whose 1.8 m view shows most of it."""
    def seen(az):
        eye = np.array([obj.center[0] + 1.8 * np.cos(np.radians(az)), obj.center[1] + 1.8 * np.sin(np.radians(az)),
                        sim.env.CAMERA_HEIGHT])
        return int((env.render_view(sim.look_at_viewmat(eye, obj.center)).instance == obj.instance_id).sum())
    return max(range(0, 360, 15), key=seen)


_PAIRS: dict = {}


def _look_alike_views(env, a_id, b_id):
    """Two views of instance ``a_id`` 15 degrees and 0.2 m apart, and one of ``b_id``, the same
    model elsewhere in the house (a look-alike)."""
    if (a_id, b_id) not in _PAIRS:
        a, b = env.house.object(a_id), env.house.object(b_id)
        assert a.class_name == b.class_name
        az_a, az_b = _open_side(env, a), _open_side(env, b)
        _PAIRS[a_id, b_id] = (_view(env, a, az_a - 15, 1.8), _view(env, a, az_a, 2.0), _view(env, b, az_b, 2.0))
    return _PAIRS[a_id, b_id]


SPECS = ["rootsift", "sift-essential", "features,detector=sift,ratio=0.75,mutual=true",
         "features,model=essential", "features,model=homography", "features,gms=true,model=none",
         "features,colour_tol=20", "features,min_inlier_ratio=0.3", "akaze"]


@pytest.mark.parametrize("spec", SPECS)
@pytest.mark.parametrize("a_id, b_id", [(32, 36), (35, 40)])  # two chairs, two TVs of one model each
def test_new_matchers_count_more_on_the_same_instance_than_on_a_look_alike(env, spec, a_id, b_id):
    if spec == "akaze" and not _has_akaze():
        pytest.skip("this OpenCV has no AKAZE (OpenCV 5 moved it to contrib)")
    m = make_matcher(spec, renders=True)
    assert isinstance(m, Matcher) and isinstance(m, LocalFeatureMatcher)
    a1, a2, b = _look_alike_views(env, a_id, b_id)
    same, other = m.count(a1, a2), m.count(a1, b)
    assert same >= RENDER_TAU_M and same > 2 * other, (spec, same, other)
    assert m.count(a1, a2) == same  # deterministic, the goal's cached features change nothing


def test_camera_and_render_presets_differ_only_in_the_contrast_threshold():
    cam, ren = make_matcher("rootsift"), make_matcher("rootsift", renders=True)
    assert (cam.contrast_threshold, ren.contrast_threshold) == (0.04, SIFTMatcher.for_renders().contrast_threshold)
    assert make_matcher("rootsift,contrast_threshold=0.03", renders=True).contrast_threshold == 0.03
    assert isinstance(make_matcher("sift", renders=True), SIFTMatcher)  # SIFT stays selectable, unchanged


def test_rootsift_is_unit_length_and_keeps_none():
    d = np.random.default_rng(0).random((5, 128)).astype(np.float32) * 100
    r = rootsift(d)
    assert r.shape == d.shape and r.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), 1.0, rtol=1e-5)
    assert rootsift(None) is None


def test_gms_keeps_coherent_motion_and_drops_scattered_matches():
    rng = np.random.default_rng(1)
    pa = rng.uniform([0, 0], [W, H], (300, 2))
    pb = pa + [12.0, -5.0]  # one coherent motion
    ra, rb = rng.uniform([0, 0], [W, H], (100, 2)), rng.uniform([0, 0], [W, H], (100, 2))
    keep = gms_filter(np.concatenate([pa, ra]), np.concatenate([pb, rb]), (H, W), (H, W))
    assert keep[:300].mean() > 0.9 and keep[300:].mean() < 0.1
    assert gms_filter(np.zeros((0, 2)), np.zeros((0, 2)), (H, W), (H, W)).shape == (0,)
    with pytest.raises(ValueError, match="differ"):
        gms_filter(np.zeros((3, 2)), np.zeros((2, 2)), (H, W), (H, W))


def test_min_inlier_ratio_zeroes_a_count_of_mostly_outliers(env):
    a1, a2, _ = _look_alike_views(env, 32, 36)
    loose, strict = LocalFeatureMatcher(), LocalFeatureMatcher(min_inlier_ratio=1.0)
    pa, _ = loose.matches(a1, a2)
    n = loose.count(a1, a2)
    assert 0 < n < len(pa)  # some filtered matches are outliers
    assert strict.count(a1, a2) == 0


def test_local_feature_matcher_bad_input():
    m = LocalFeatureMatcher()
    img = np.random.default_rng(0).random((H, W, 3)).astype(np.float32)
    with pytest.raises(ValueError, match="goal"):
        m.count(img[..., 0], img)
    with pytest.raises(ValueError, match="image"):
        m.count(img, np.full_like(img, np.nan))
    for kw, match in (({"detector": "orb"}, "detector"), ({"ratio": 1.0}, "ratio"),
                      ({"ratio": None, "mutual": False}, "ratio test"), ({"model": "affine"}, "model"),
                      ({"ransac_thresh": 0}, "ransac_thresh"), ({"min_matches": 4}, "min_matches"),
                      ({"min_inlier_ratio": 1.5}, "min_inlier_ratio"), ({"colour_tol": 0}, "colour_tol"),
                      ({"hfov_deg": 180}, "hfov_deg"), ({"contrast_threshold": 0}, "contrast_threshold")):
        with pytest.raises(ValueError, match=match):
            LocalFeatureMatcher(**kw)
    with pytest.raises(ValueError, match="unknown option"):
        make_matcher("rootsift,sam=3")
    if not _has_akaze():
        with pytest.raises(ImportError, match="contrib"):
            LocalFeatureMatcher("akaze").count(img, img)


def test_a_flat_image_gives_zero_for_every_model():
    flat = np.full((H, W, 3), 0.5, np.float32)
    tex = np.random.default_rng(2).random((H, W, 3)).astype(np.float32)
    for model in ("fundamental", "homography", "essential", "none"):
        assert LocalFeatureMatcher(model=model).count(tex, flat) == 0


# -- the separation measure -------------------------------------------------------------------

def test_roc_auc_on_a_hand_made_case():
    # pairs: 3>1, 3>2, 2>1, 2=2 (half) -> 3.5 / 4
    assert roc_auc([3, 2], [1, 2]) == pytest.approx(0.875)
    assert roc_auc([5, 6], [1, 2, 3]) == 1.0 and roc_auc([1], [2]) == 0.0 and roc_auc([4], [4]) == 0.5
    with pytest.raises(ValueError, match="at least one"):
        roc_auc([], [1])
    with pytest.raises(ValueError, match="finite"):
        roc_auc([np.nan], [1])


def test_separation_pairs_each_goal_with_its_best_look_alike():
    from nvsm_separation import separation

    recs = [{"episode": "a", "instance": 1, "is_goal": True, "best": 20},
            {"episode": "a", "instance": 2, "is_goal": False, "best": 9},
            {"episode": "a", "instance": 3, "is_goal": False, "best": 12},
            {"episode": "b", "instance": 1, "is_goal": True, "best": 10},
            {"episode": "b", "instance": 4, "is_goal": False, "best": 10},
            {"episode": "c", "instance": 5, "is_goal": False, "best": 7}]  # no goal views: unpaired
    s = separation(recs)
    # positives 20, 10 vs negatives 9, 12, 10, 7: 20 beats all 4, 10 beats 9 and 7 and ties 10 -> 6.5 / 8
    assert s["auc"] == pytest.approx(6.5 / 8)
    assert (s["episodes"], s["wins"], s["ties"], s["losses"]) == (2, 1, 1, 0)
    assert (s["n_goal"], s["n_lookalike"]) == (2, 4) and s["mean_margin"] == pytest.approx(4.0)
    assert separation(recs[:1])["auc"] is None


# -- the dumper -------------------------------------------------------------------------------

def _goal_chair_episode():
    """Dev house 0's chair episode, started facing the goal chair (it fills the first frame)."""
    import nvsm_views as nv

    ep = nv.dev_episodes(4)[3]
    assert ep.house_seed == 0 and ep.goal_class == "chair"
    return dataclasses.replace(ep, start=[6.475, 1.325, -1.6313])


@pytest.mark.slow  # two full dumps of an episode (about 40 s on 2 cores)
def test_dumper_is_deterministic(tmp_path):
    """A second run of the same episode writes the same arrays."""
    import nvsm_views as nv

    ep = _goal_chair_episode()
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    nv.dump_episode(ep, str(a), max_steps=3)
    nv.dump_episode(ep, str(b), max_steps=3)
    da, db = nv.load_views(str(a)), nv.load_views(str(b))
    assert set(da) == set(db)
    for k, v in da.items():
        if isinstance(v, np.ndarray):
            np.testing.assert_array_equal(v, db[k], err_msg=k)


@pytest.mark.slow  # a three-step agent episode with the NVSM dump, about 15 s on 2 cores
def test_dumper_writes_a_loadable_file(tmp_path):
    """A three-step episode that starts facing the goal chair of dev house 0: the supplement
    verifies both chairs the robot saw, and the file holds the views the separation scores."""
    import nvsm_views as nv
    from nvsm_separation import object_scores

    ep = _goal_chair_episode()
    a = tmp_path / "a.npz"
    s = nv.dump_episode(ep, str(a), max_steps=3)
    da = nv.load_views(str(a))
    assert s["runs"] >= 2 and s["goal_verified"]
    V = len(da["view_run"])
    assert da["rendered"].shape == da["opencv"].shape == (V, H, W, 3) and da["rendered"].dtype == np.uint8
    assert da["holes"].shape == da["background"].shape == da["alpha"].shape == (V, H, W)
    assert not np.any(da["holes"] & da["background"])
    # what was inpainted is only the holes
    np.testing.assert_array_equal(da["rendered"][~da["holes"]], da["opencv"][~da["holes"]])
    assert da["run_is_goal"].any() and (~da["run_is_goal"]).any()
    assert set(da["run_source"]) <= {"agent", "supplement"}
    # the online map's renders of the same cameras, for nvsm_separation.py --fill
    assert da["local"].shape == da["grgb"].shape == da["gcrgb"].shape == (V, H, W, 3)
    assert da["galpha"].shape == da["gcalpha"].shape == (V, H, W) and da["galpha"].any()
    assert da["episode"]["goal_instance_id"] == ep.goal_instance_id and json.dumps(da["meta"])
    recs = object_scores([str(a)], SIFTMatcher.for_renders(), "opencv")
    assert {r["is_goal"] for r in recs} == {True, False}
    # the stored views reproduce the agent's own counts (same matcher, same images)
    if da["meta"]["agent_inpainter"] == "OpenCVInpainter" and "SIFTMatcher" in da["meta"]["agent_nvsm_matcher"]:
            assert max(r["best"] for r in recs if r["is_goal"]) == max(
            c for c, g in zip(da["run_agent_counts_max"], da["run_is_goal"]) if g)


def test_separation_gives_a_learned_completion_the_holes_the_nvsm_gives_it():
    """A ``completes_background`` inpainter (the VCICN) gets the interior holes and the cropped-away
    background, as verify_object gives it; any other plug-in, or ``holes_mode="interior"``, only
    the interior holes."""
    from nvsm_separation import _views_of

    rng = np.random.default_rng(0)
    holes = np.zeros((2, 6, 8), bool)
    holes[:, 2:4, 3:5] = True
    background = np.zeros_like(holes)
    background[:, :, :1] = True
    d = {"view_run": np.array([0, 0]), "rendered": rng.integers(0, 255, (2, 6, 8, 3), dtype=np.uint8),
         "holes": holes, "background": background, "viewmats": np.stack([np.eye(4)] * 2),
         "alpha": np.zeros((2, 6, 8), np.uint8), "K": np.eye(3)}

    class Recorder:
        def __init__(self, learned):
            self.completes_background, self.got = learned, None

        def inpaint(self, images, masks):
            self.got = masks.copy()
            return images

    learned, single = Recorder(True), Recorder(False)
    _views_of(d, 0, learned, "vcicn")
    _views_of(d, 0, single, "opencv-like")
    np.testing.assert_array_equal(learned.got, holes | background)
    np.testing.assert_array_equal(single.got, holes)
    _views_of(d, 0, learned, "vcicn", holes_mode="interior")
    np.testing.assert_array_equal(learned.got, holes)


def test_apply_fill_composites_the_online_map_and_finds_the_holes_again():
    """--fill: an empty online map gives back the stored views; an opaque one covers every hole
    and shows through where the local render was empty."""
    from nvsm_separation import apply_fill
    from nvsm_views import _u8, split_views

    alpha = np.ones((1, 8, 10), np.float32)
    alpha[:, :, :2] = 0.0  # background at the left border
    alpha[:, 4:6, 5:7] = 0.0  # an enclosed gap
    local = np.repeat(np.where(alpha[..., None] > 0, 0.8, 0.0), 3, axis=-1).astype(np.float32)
    rendered, holes, bg = split_views(local, alpha < 0.5, alpha, 0.5, 0.5)
    d = {"local": _u8(local), "alpha": _u8(alpha), "rendered": _u8(rendered), "holes": holes, "background": bg,
         "opencv": _u8(rendered), "grgb": np.zeros((1, 8, 10, 3), np.uint8), "galpha": np.zeros((1, 8, 10), np.uint8)}
    assert apply_fill(d, "none") is d
    same = apply_fill(d, "global")
    for k in ("rendered", "holes", "background"):
        np.testing.assert_array_equal(same[k], d[k], err_msg=k)
    d["grgb"], d["galpha"] = np.full((1, 8, 10, 3), 51, np.uint8), np.full((1, 8, 10), 255, np.uint8)
    full = apply_fill(d, "global")
    assert not full["holes"].any() and not full["background"].any()
    np.testing.assert_array_equal(full["rendered"][alpha < 0.5], 51)
    np.testing.assert_array_equal(full["rendered"][alpha >= 0.5], 204)
    with pytest.raises(ValueError, match="online-map"):
        apply_fill(d, "global-crop")


def test_stored_views_do_not_depend_on_the_agents_completion():
    """A VCICN agent's NVSM keeps the background in its holes, black; the dumper stores it split
    off and grey, as the NVSM gives raw and OpenCV views, and leaves an OpenCV agent's views as
    they were."""
    from nvsm_views import split_views

    alpha = np.ones((1, 8, 10), np.float32)
    alpha[:, :, :2] = 0.0  # background at the left border
    alpha[:, 4:6, 5:7] = 0.0  # an enclosed gap
    full = alpha < 0.5
    rgb = np.full((1, 8, 10, 3), 0.8, np.float32)
    rgb[full] = 0.0
    out, holes, bg = split_views(rgb, full, alpha, 0.5, 0.5)
    assert holes.sum() == 4 and holes[0, 4:6, 5:7].all()
    np.testing.assert_array_equal(bg, full & ~holes)
    np.testing.assert_allclose(out[bg], 0.5)
    np.testing.assert_allclose(out[holes], 0.0)
    # an OpenCV agent's run: holes already interior, background already grey -> unchanged
    out2, holes2, bg2 = split_views(out, holes, alpha, 0.5, 0.5)
    np.testing.assert_array_equal(out2, out)
    np.testing.assert_array_equal(holes2, holes)
    np.testing.assert_array_equal(bg2, bg)


# -- re-rendering stored runs ------------------------------------------------------------------

def test_inside_box_keeps_only_surface_points_in_the_box():
    """A wall 2 m in front of an identity camera: only the pixels whose wall point lies in the
    box's x range are inside; invalid depth is never inside."""
    from nvsm_rerender import _inside_box

    K = np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]])
    depth = np.full((80, 100), 2.0, np.float32)
    depth[:, :5] = 0.0
    box = (np.array([0.0, -5.0, 0.0]), np.array([5.0, 5.0, 5.0]))  # x >= 0: the right half of the image
    m = _inside_box(depth, np.eye(4), K, box)
    assert m.shape == depth.shape and set(np.unique(m)) <= {0.0, 1.0}
    assert m[:, 50:].all() and not m[:, :50].any()


@pytest.mark.slow
def test_rerender_reproduces_the_agents_views_and_renders_the_truth_in_the_region(tmp_path):
    """The dumper stores each run's observations (the agent's and the larger shadow set); the
    re-built local map renders what the agent rendered, and the truth-region source renders
    the ray caster's images of the same cameras with nothing outside the crop box."""
    import nvsm_views as nv
    from nvsm_rerender import rerender_file

    from splatsearch.sim.episodes import house_for_episode

    ep = nv.dev_episodes(4)[3]
    ep = dataclasses.replace(ep, start=[6.475, 1.325, -1.6313])
    path = tmp_path / "a.npz"
    nv.dump_episode(ep, str(path), max_steps=3)
    d = nv.load_views(str(path))
    R = len(d["run_entry"])
    for pre in ("obs", "xobs"):
        F = len(d[f"{pre}_run"])
        assert F >= R and set(d[f"{pre}_run"]) == set(range(R))
        assert d[f"{pre}_rgb"].shape == (F, H, W, 3) and d[f"{pre}_depth"].dtype == np.uint16
    assert d["run_bbox_min"].shape == d["run_centroid"].shape == (R, 3)
    assert np.all(d["run_bbox_min"] <= d["run_bbox_max"])
    # the agent's store keeps at most max_frames per object; the shadow at least as many
    for r in range(R):
        assert (d["obs_run"] == r).sum() <= (d["xobs_run"] == r).sum() <= nv.SHADOW_FRAMES
    m = rerender_file(d, source="map")
    assert m["rendered"].shape == d["rendered"].shape and m["view_run"].tolist() == d["view_run"].tolist()
    # the same map up to the stored observations' quantisation (uint8 colour, millimetre depth)
    diff = np.abs(m["rendered"].astype(float) - d["rendered"].astype(float))
    assert np.median(diff) <= 2 and diff.mean() < 8
    env = sim.HouseEnv(house_for_episode(ep), width=W, height=H)
    # a 0.2 m region: the 3 m default can hold everything these cameras see in a small room
    t = rerender_file(d, source="truth-region", env=env, margin=0.2)
    v0 = d["viewmats"][0]
    np.testing.assert_allclose(t["rendered"][0][t["alpha"][0] == 255] / 255.0,
                               env.render_view(v0).rgb[t["alpha"][0] == 255], atol=1 / 255 + 1e-6)
    # outside the region: background filled flat, or enclosed holes the inpainter completes
    assert (t["alpha"] == 0).any() and (t["background"] | t["holes"])[t["alpha"] == 0].all()
    assert (t["rendered"][t["background"]] == 128).all()
    with pytest.raises(ValueError, match="frames"):
        rerender_file(d, frames="more")
