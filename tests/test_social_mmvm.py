"""CoNVOI's multi-modal visual marking: homographies, line of sight, numbering, rendering."""

import numpy as np
import pytest
from splatsearch.social.convoi.geometry import distance_field_from_capsules
from splatsearch.social.convoi.mmvm import (
    CameraModel,
    MarkerGrid,
    apply_homography,
    candidate_grid,
    crop_patch,
    grid_to_image_homography,
    line_of_sight,
    mark,
    render_view,
    select_candidates,
)
from splatsearch.social.convoi.perception import local_maps
from splatsearch.social.convoi.scenarios import GRID

CAM = CameraModel.from_fov(320, 240, 90.0, height_m=0.6, pitch=-0.35)


def test_ground_homography_round_trips_and_matches_the_3d_projection():
    rng = np.random.default_rng(0)
    xy = np.stack([rng.uniform(0.8, 6.0, 200), rng.uniform(-2.0, 2.0, 200)], -1)
    uv, _ = CAM.project_ground(xy)
    back, ok2 = CAM.unproject_pixels(uv)
    np.testing.assert_allclose(back, xy, atol=1e-6)
    assert ok2.all()
    # the same pixels from a full 3-D pinhole projection with the simulator's camera convention
    from splatsearch.sim import camera_viewmat

    vm = camera_viewmat(CAM.forward, 0.0, 0.0, CAM.height_m, CAM.pitch)
    np.testing.assert_allclose(vm, CAM.viewmat(), atol=1e-12)
    pc = (vm @ np.c_[xy, np.zeros(len(xy)), np.ones(len(xy))].T)[:3]
    proj = (CAM.Kmat @ pc).T
    np.testing.assert_allclose(uv, proj[:, :2] / proj[:, 2:], atol=1e-6)
    # pixel -> ground -> pixel too, and pixels above the horizon do not reach the ground
    px = np.stack([rng.uniform(0, 320, 100), rng.uniform(120, 240, 100)], -1)
    g, hit = CAM.unproject_pixels(px)
    assert hit.all()
    np.testing.assert_allclose(CAM.project_ground(g)[0], px, atol=1e-6)
    assert not CAM.unproject_pixels(np.array([[160.0, 5.0]]))[1][0]
    # points behind the camera are never "in the image"
    assert not CAM.project_ground(np.array([[-2.0, 0.0]]))[1][0]


def test_cell_homography_eq3_matches_cell_centres():
    lm, _ = local_maps(distance_field_from_capsules(np.zeros((0, 5), np.float32), GRID), [0.0, 0.0, 0.0])
    H = grid_to_image_homography(lm.spec, CAM)
    rc = np.array([[100, 140], [90, 160], [120, 130]])  # (row, col) cells ahead of the robot
    uv = apply_homography(H, rc[:, ::-1].astype(float))
    uv2, _ = CAM.project_ground(lm.spec.cell_to_world(rc))
    np.testing.assert_allclose(uv, uv2, atol=1e-6)
    back = apply_homography(np.linalg.inv(H), uv)
    np.testing.assert_allclose(back, rc[:, ::-1], atol=1e-6)


def corridor_maps(people=None, pose=(0.0, 0.0, 0.0)):
    caps = np.array([[-2, -1.2, 12, -1.2, 0.05], [-2, 1.2, 12, 1.2, 0.05], [3.0, 0.0, 3.0, 0.0, 0.3]], np.float32)
    return local_maps(distance_field_from_capsules(caps, GRID), pose, people)


def test_line_of_sight_eq2_and_candidate_numbering():
    _, full = corridor_maps(people=[[1.5, -0.6]])
    grid = MarkerGrid(rows=3, cols=7, d_row=1.2, d_col=0.4, first_row=1.2)
    g = candidate_grid(grid)
    assert g.shape == (3, 7, 2) and g[0, 0, 1] > g[0, -1, 1]  # column 0 is the leftmost
    los = line_of_sight(full, g)
    assert los[0, 3]  # straight ahead at 1.2 m is clear
    assert not los[2, 3]  # straight ahead at 3.6 m is behind the pillar
    assert not los[1, 5]  # (2.4, -0.8): hidden by the person at (1.5, -0.6)
    assert not los[0, 0] and not los[0, 6]  # +-1.2 m: in the (inflated) walls
    m = select_candidates(full, CAM, grid)
    assert np.array_equal(m.labels, np.arange(1, len(m.labels) + 1))
    assert np.all(np.diff(m.row) >= 0)  # row by row, nearest first
    for r in set(m.row.tolist()):
        assert np.all(np.diff(m.pixels[m.row == r, 0]) > 0)  # left to right in the image
    assert all(los[i, j] for i, j in zip(m.row, m.col))
    np.testing.assert_allclose(m.lookup([m.labels[-1], m.labels[0]]), m.robot_xy[[-1, 0]])
    with pytest.raises(ValueError, match="not marked"):
        m.lookup([999])


def test_mark_draws_numbers_and_render_view_shows_the_scene():
    static, full = corridor_maps(people=[[2.0, 0.6]])
    img = render_view(static, CAM, [[2.0, 0.6]])
    assert img.shape == (240, 320, 3) and img.dtype == np.float32
    assert 0.0 <= img.min() and img.max() <= 1.0
    uv, _ = CAM.project_ground(np.array([[2.0, 0.6]]))
    u, v = np.round(uv[0]).astype(int)
    assert img[v, u, 0] > img[v, u, 2] + 0.3  # the first person's red shirt is where the person stands
    marked, markers = mark(img, full, CAM, MarkerGrid())
    assert marked.dtype == np.uint8 and len(markers.labels) > 0
    base = (img * 255).astype(np.uint8)
    for (u, v) in markers.pixels.astype(int):
        win = np.s_[max(v - 4, 0):v + 5, max(u - 4, 0):u + 5]
        assert np.abs(marked[win].astype(int) - base[win].astype(int)).sum() > 0  # a number was drawn there
    assert crop_patch(img, (160, 200), 32).shape == (32, 32, 3)
    assert crop_patch(img, (-5, 10), 32) is None
    with pytest.raises(ValueError, match="image"):
        mark(np.zeros((10, 10, 3)), full, CAM, MarkerGrid())
