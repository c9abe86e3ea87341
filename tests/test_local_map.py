"""Object-local maps for the NVSM: observation store, region masking, the map itself."""

import numpy as np
import pytest

from splatsearch import sim
from splatsearch.search.local_map import (
    LocalMapConfig,
    ObservationStore,
    build_local_map,
    region_box,
    region_frame,
)
from splatsearch.search.novel_views import render_novel_views

W, H = 160, 120


@pytest.fixture(scope="module")
def env():
    return sim.HouseEnv(sim.make_house(0), width=W, height=H)


_OPEN: dict = {}


def _view(env, obj, az_deg, dist):
    """Frame of ``obj`` from ``dist`` m at ``az_deg`` from its most open side (furniture often
    stands against a wall)."""
    if obj.instance_id not in _OPEN:
        def seen(a):
            eye = np.array([obj.center[0] + 1.8 * np.cos(a), obj.center[1] + 1.8 * np.sin(a), sim.env.CAMERA_HEIGHT])
            return int((env.render_view(sim.look_at_viewmat(eye, obj.center)).instance == obj.instance_id).sum())
        _OPEN[obj.instance_id] = max(np.radians(np.arange(0, 360, 15)), key=seen)
    az = _OPEN[obj.instance_id] + np.radians(az_deg)
    eye = np.array([obj.center[0] + dist * np.cos(az), obj.center[1] + dist * np.sin(az), sim.env.CAMERA_HEIGHT])
    return env.render_view(sim.look_at_viewmat(eye, obj.center))


def _vm_at(x, y, yaw):
    eye = np.array([x, y, 1.3])
    return sim.look_at_viewmat(eye, eye + np.array([np.cos(yaw), np.sin(yaw), 0.0]))


def test_observation_store_keeps_diverse_viewpoints():
    store = ObservationStore(max_frames=3, min_separation=0.3)
    rgb, depth = np.zeros((4, 5, 3), np.float32), np.ones((4, 5), np.float32)
    store.add(0, rgb, depth, _vm_at(0, 0, 0))
    store.add(0, rgb + 0.5, depth, _vm_at(0.1, 0, 0))  # the same viewpoint: replaces, newest wins
    assert len(store[0]) == 1 and store[0][0].rgb[0, 0, 0] == 0.5
    store.add(0, rgb, depth, _vm_at(3, 0, 0))
    store.add(0, rgb, depth, _vm_at(0, 3, 1.5))
    store.add(0, rgb, depth, _vm_at(0.5, 0, 0))  # full: the most redundant of the close pair goes
    centres = sorted(tuple(np.round(-f.viewmat[:3, :3].T @ f.viewmat[:3, 3], 1)[:2]) for f in store[0])
    assert len(centres) == 3
    assert (3.0, 0.0) in centres and (0.0, 3.0) in centres
    assert store[1] == []
    with pytest.raises(ValueError):
        store.add(0, rgb, np.ones((3, 3), np.float32), _vm_at(0, 0, 0))
    with pytest.raises(ValueError):
        ObservationStore(max_frames=0)


def test_region_frame_blanks_points_outside_the_box(env):
    obj = next(o for o in env.house.objects if o.class_name == "chair")
    f = _view(env, obj, 0, 2.0)
    lo, hi = region_box(obj.center - obj.size / 2, obj.center + obj.size / 2, 0.1)
    rgb, depth = region_frame(f.rgb, f.depth, f.viewmat, env.K, lo, hi)
    on_obj = f.instance == obj.instance_id
    kept = depth > 0
    # the object's pixels are kept (bar a rim where the box edge cuts them) and little else
    assert kept[on_obj].mean() > 0.95
    assert kept.sum() < 1.5 * on_obj.sum()
    assert np.all(rgb[~kept] == 0) and np.array_equal(rgb[kept], f.rgb[kept])
    with pytest.raises(ValueError):
        region_box([0, 0, 0], [-1, 0, 0], 0.0)


def test_local_map_renders_the_object_from_a_new_viewpoint(env):
    obj = next(o for o in env.house.objects if o.class_name == "chair")
    frames = [_view(env, obj, a, 1.8) for a in (-30, 0, 30)]
    lo, hi = region_box(obj.center - obj.size / 2, obj.center + obj.size / 2, 0.5)
    gmap = build_local_map(frames, env.K, W, H, lo, hi, LocalMapConfig(iters_per_frame=4, refine_iters=8))
    means = np.asarray(gmap.means)[np.asarray(gmap.active)]
    assert len(means) > 100
    assert np.all(means >= lo - 0.05) and np.all(means <= hi + 0.05)  # nothing outside the region
    # a held-out view between the training ones sees the object where the simulator does
    test = _view(env, obj, 15, 1.8)
    rgb, alpha = render_novel_views(gmap, test.viewmat[None], env.K, W, H)
    on_obj = test.instance == obj.instance_id
    assert alpha[0][on_obj].mean() > 0.8
    err = np.abs(rgb[0] - test.rgb).mean(-1)[on_obj].mean()
    assert err < 0.1
    with pytest.raises(ValueError):
        build_local_map([], env.K, W, H, lo, hi)


def test_default_local_map_is_sharper_than_the_stride_2_map(env):
    # the NVSM's matches live on the covered part of the render: the default densifies every
    # pixel, which renders a held-out view closer to the simulator's than a stride-2 map
    obj = next(o for o in env.house.objects if o.class_name == "chair")
    frames = [_view(env, obj, a, 1.8) for a in (-30, 0, 30)]
    lo, hi = region_box(obj.center - obj.size / 2, obj.center + obj.size / 2, 0.5)
    test = _view(env, obj, 15, 1.8)
    on_obj = test.instance == obj.instance_id
    errs, counts = {}, {}
    for name, cfg in (("default", LocalMapConfig()), ("stride2", LocalMapConfig(stride=2))):
        gmap = build_local_map(frames, env.K, W, H, lo, hi, cfg)
        counts[name] = int(np.asarray(gmap.active).sum())
        rgb, _ = render_novel_views(gmap, test.viewmat[None], env.K, W, H)
        errs[name] = float(np.abs(rgb[0] - test.rgb).mean(-1)[on_obj].mean())
    assert LocalMapConfig().stride == 1
    assert counts["default"] > 2 * counts["stride2"]
    assert errs["default"] < errs["stride2"]
