"""Trajectory metrics against independent oracles (similaritymeasures, SciPy, numpy loops)."""

import numpy as np
import pytest
import similaritymeasures as sm
from scipy.spatial.distance import cosine as scipy_cosine
from scipy.spatial.distance import directed_hausdorff
from splatsearch.nav.grid import GridSpec
from splatsearch.social.convoi import metrics as M
from splatsearch.social.convoi.geometry import distance_field_from_capsules

RNG = np.random.default_rng(7)
PAIRS = [(np.cumsum(RNG.normal(size=(n, 2)), 0), np.cumsum(RNG.normal(size=(m, 2)), 0))
         for n, m in ((12, 20), (57, 33), (100, 100), (5, 1))]


def np_resample(a, n):
    # independent oracle: numpy interpolation along the cumulative arc length
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(a, axis=0), axis=1))]
    q = np.linspace(0, s[-1], n)
    return np.stack([np.interp(q, s, a[:, 0]), np.interp(q, s, a[:, 1])], -1)


@pytest.mark.parametrize("a,b", PAIRS)
def test_frechet_matches_similaritymeasures(a, b):
    assert M.frechet(a, b) == pytest.approx(sm.frechet_dist(a, b), rel=1e-5, abs=1e-5)


@pytest.mark.parametrize("a,b", PAIRS)
def test_hausdorff_matches_scipy(a, b):
    ref = max(directed_hausdorff(a, b)[0], directed_hausdorff(b, a)[0])
    assert M.hausdorff(a, b) == pytest.approx(ref, rel=1e-5, abs=1e-5)


@pytest.mark.parametrize("a,b", PAIRS[:3])
def test_mse_and_length_match_similaritymeasures(a, b):
    np.testing.assert_allclose(M.resample(a, 64), np_resample(a, 64), atol=1e-4)
    # similaritymeasures.mse averages over coordinates; ours sums the squared x and y errors
    ref = 2 * sm.mse(np_resample(a, 80), np_resample(b, 80))
    assert M.mse(a, b, 80) == pytest.approx(ref, rel=1e-4)
    assert M.path_length(a) == pytest.approx(sm.get_arc_length(a)[0], rel=1e-5)


def test_padding_does_not_change_values():
    a, b = PAIRS[1]
    padded = np.vstack([a, np.repeat(a[-1:], 40, 0)])
    assert M.frechet(padded, b) == pytest.approx(M.frechet(a, b), rel=1e-6)
    assert M.hausdorff(padded, b) == pytest.approx(M.hausdorff(a, b), rel=1e-6)
    assert M.path_length(padded) == pytest.approx(M.path_length(a), rel=1e-6)


def test_normalised_length_and_mean_velocity():
    t = np.linspace(0, np.pi, 101)
    half_circle = np.stack([1 - np.cos(t), np.sin(t)], -1)  # radius 1 from (0, 0) to (2, 0)
    assert M.normalized_length(half_circle) == pytest.approx(np.pi / 2, rel=1e-3)
    assert M.normalized_length(half_circle, (0, 0), (4, 0)) == pytest.approx(np.pi / 4, rel=1e-3)
    assert M.mean_velocity(half_circle, 0.1) == pytest.approx(sm.get_arc_length(half_circle)[0] / 10.0, rel=1e-5)
    with pytest.raises(ValueError):
        M.normalized_length(half_circle, (1, 1), (1, 1))


def people_case():
    T = 50
    robot = np.stack([np.linspace(0, 5, T), np.zeros(T)], -1)
    people = np.zeros((T, 3, 2))
    people[:, 0] = [2.5, 0.6]  # standing beside the path
    people[:, 1] = np.stack([np.linspace(5, 0, T), np.full(T, -1.5)], -1)  # walking by, far
    people[:, 2] = [2.0, 0.3]  # an inactive slot that must be ignored
    return robot, people, np.array([True, True, False])


def test_psv_min_distance_and_collisions_against_a_loop():
    robot, people, valid = people_case()
    dt, rr, pr = 0.1, 0.25, 0.05
    gaps = np.array([min(np.linalg.norm(robot[t] - people[t, i]) - rr - pr for i in range(3) if valid[i])
                     for t in range(len(robot))])
    for zone in (0.1, 0.25, 0.5):
        assert M.psv_duration(robot, people, dt, zone, valid, rr, pr) == pytest.approx((gaps < zone).sum() * dt)
    zones = M.psv_duration(robot, people, dt, (0.1, 0.5, 1.2), valid, rr, pr)
    np.testing.assert_allclose(zones, [(gaps < z).sum() * dt for z in (0.1, 0.5, 1.2)])
    assert M.min_distance_to_people(robot, people, valid, rr, pr) == pytest.approx(gaps.min(), abs=1e-5)
    centre = min(np.linalg.norm(robot[t] - people[t, i]) for t in range(len(robot)) for i in range(2))
    assert M.min_distance_to_people(robot, people, valid) == pytest.approx(centre, abs=1e-5)
    assert M.collision_count(robot, people, valid, 0.25, 0.25) == 0
    assert M.collision_count(robot, people, valid, 0.4, 0.3) == 1  # one continuous overlap = one collision
    assert M.success(True, 0) and not M.success(True, 1) and not M.success(False, 0)


def test_collisions_with_walls_use_the_field():
    field = distance_field_from_capsules(np.array([[2.0, -1.0, 2.0, 1.0, 0.05]], np.float32),
                                         GridSpec((-1.0, -2.0), 0.05, (80, 100)))
    robot = np.stack([np.linspace(0, 1.9, 20), np.zeros(20)], -1)
    people = np.full((20, 1, 2), 50.0)
    assert M.collision_count(robot, people, None, 0.25, 0.25) == 0
    assert M.collision_count(robot, people, None, 0.25, 0.25, field=field) == 1


def test_reference_path_metrics():
    gt = np.array([[1.0, -0.5], [2.0, -0.5], [3.0, -0.5]])
    pred = np.array([[1.0, 0.0], [2.0, 0.5]])
    assert M.reference_path_error(pred, gt) == pytest.approx(np.linalg.norm(pred.mean(0) - gt.mean(0)))
    assert M.cosine_similarity(pred, gt) == pytest.approx(1 - scipy_cosine(pred.mean(0), gt.mean(0)), abs=1e-6)
    assert M.cosine_similarity(gt, gt) == pytest.approx(1.0)
    assert M.fraction_unacceptable([True, False, False, True]) == 0.5
    assert M.fraction_unacceptable([]) == 0.0


def test_unacceptable_paths():
    # robot frame: a wall across x = 2 with a gap for y in [-0.5, 0.5]
    spec = GridSpec.centered((0.0, 0.0), (160, 160), 0.05)
    field = distance_field_from_capsules(np.array([[2.0, 0.5, 2.0, 4.0, 0.05], [2.0, -0.5, 2.0, -4.0, 0.05]],
                                                  np.float32), spec)
    through_gap = np.array([[1.0, 0.0], [3.0, 0.0]])
    through_wall = np.array([[1.0, 1.5], [3.0, 1.5]])
    assert not M.path_unacceptable(through_gap, field, clearance=0.2)
    assert M.path_unacceptable(through_wall, field, clearance=0.2)
    people = np.array([[1.0, 2.5], [1.0, 3.5], [2.5, 0.0]])
    assert M.path_unacceptable(through_gap, field, clearance=0.2, people=people)  # runs into a person
    left = np.array([[1.0, 2.2], [1.0, 3.0]])  # between two members of a group (people 0 and 1)
    assert M.path_unacceptable(left[:1].tolist() + [[1.0, 3.0]], field, clearance=0.0, people=people[:2],
                               group_pairs=[[0, 1]])
    assert not M.path_unacceptable([[1.0, 1.0]], field, clearance=0.0, people=people[:2], group_pairs=[[0, 1]])


def test_bad_inputs_raise():
    with pytest.raises(ValueError):
        M.frechet(np.zeros((3, 1)), np.zeros((3, 2)))
    with pytest.raises(ValueError):
        M.hausdorff([[0.0, np.nan]], [[0.0, 0.0]])
    with pytest.raises(ValueError):
        M.psv_duration(np.zeros((5, 2)), np.zeros((4, 1, 2)), 0.1)
    with pytest.raises(ValueError):
        M.mean_velocity(np.zeros((5, 2)), 0.0)


def test_pad_rows_pads_masks_and_guards_capacity():
    from splatsearch.social.convoi.geometry import pad_rows

    out, valid = pad_rows([[1, 2], [3, 4]], 4)
    assert out.shape == (4, 2) and out.dtype == np.float32 and valid.tolist() == [True, True, False, False]
    assert out[:2].tolist() == [[1, 2], [3, 4]] and not out[2:].any()
    out, valid = pad_rows(None, 3, np.int32)
    assert out.dtype == np.int32 and not valid.any()
    with pytest.raises(ValueError, match="group pairs"):
        pad_rows(np.zeros((5, 2)), 4, what="group pairs")
    out, valid = pad_rows(np.arange(10).reshape(5, 2), 4, truncate=True)
    assert valid.all() and out[-1].tolist() == [6, 7]


def test_social_metrics_seanav_style():
    from splatsearch.social.convoi.metrics import path_irregularity, social_metrics, time_not_moving

    T = 21
    x = np.linspace(0, 4, T)
    straight = np.stack([x, 0 * x, 0 * x], -1)
    assert path_irregularity(straight) == pytest.approx(0.0)
    weave = straight.copy()
    weave[:, 2] = 0.3 * np.sin(np.arange(T))
    assert path_irregularity(weave) > 0.5  # about 0.87 rad/m of pointless turning
    turn = straight.copy()
    turn[:, 2] = np.linspace(0, np.pi / 2, T)  # one monotone turn: nothing beyond what it needs
    assert path_irregularity(turn) == pytest.approx(0.0, abs=1e-9)
    still = np.concatenate([straight[:5], np.repeat(straight[5:6], 10, 0), straight[5:]])
    assert time_not_moving(still[:, :2], 0.1) == pytest.approx(1.0)  # 11 equal poses: 10 steps still
    # one person standing 1.0 m beside the path (edge gap 0.5 m): personal zone, never intimate
    people = np.broadcast_to(np.array([[[2.0, 1.0]]]), (T, 1, 2))
    m = social_metrics(straight, people, np.array([True]), 0.1, True)
    assert m["completed"] == 1.0 and m["intimate_s"] == 0.0
    assert m["min_dist"] == pytest.approx(0.5, abs=1e-5)
    gaps = np.hypot(x - 2.0, 1.0) - 0.5
    assert m["personal_s"] == pytest.approx(0.1 * np.sum(gaps < 1.2))
