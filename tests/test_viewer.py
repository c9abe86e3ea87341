"""Viewer helpers, and a headless-chromium test that the splats are really drawn."""

import contextlib
import shutil
import socket
import subprocess
import tempfile
import time

import numpy as np
import pytest

from splatsearch.viewer import (
    SearchViewer,
    check_port,
    covariances_from,
    decimate,
    framing_camera,
    grid_rgba,
    scalar_rgba,
)

CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--enable-unsafe-swiftshader", "--use-angle=swiftshader",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--no-first-run"]


def _grey(img: np.ndarray) -> np.ndarray:
    """Pixels of the free-space plane's light grey."""
    return np.abs(img[..., :3].astype(int) - 225).max(-1) < 20


def _free_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def test_covariances_match_rotation_and_scales():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(5, 4)).astype(np.float32)
    s = rng.uniform(0.01, 0.5, (5, 3)).astype(np.float32)
    cov = covariances_from(s, q)
    np.testing.assert_allclose(cov, np.swapaxes(cov, 1, 2), atol=1e-7)
    # eigenvalues are the squared scales, whatever the rotation
    np.testing.assert_allclose(np.sort(np.linalg.eigvalsh(cov), 1), np.sort(s**2, 1), rtol=1e-4, atol=1e-7)


def test_decimate_keeps_the_most_covering_gaussians():
    op = np.array([0.9, 0.1, 0.9, 0.5], np.float32)
    sc = np.array([[0.1] * 3, [0.1] * 3, [0.01] * 3, [0.2] * 3], np.float32)
    np.testing.assert_array_equal(decimate(op, sc, 2), [0, 3])
    np.testing.assert_array_equal(decimate(op, sc, 10), [0, 1, 2, 3])


def test_grid_textures_are_transparent_where_unknown():
    grid = np.array([[0, 1], [2, 1]])
    rgba = grid_rgba(grid, {1: (200, 200, 200, 170), 2: (0, 0, 0, 255)}, upsample=3)
    assert rgba.shape == (6, 6, 4)
    assert (rgba[:3, :3, 3] == 0).all()  # unknown (0) is transparent
    assert (rgba[3:, :3] == (0, 0, 0, 255)).all()  # row 1 stays row 1: no flip
    vals = scalar_rgba(np.array([[0.0, 1.0]]), np.array([[True, False]]), upsample=1)
    assert vals[0, 0, 3] > 0 and vals[0, 1, 3] == 0


needs_chromium = pytest.mark.skipif(shutil.which("chromium") is None,
                                    reason="chromium is not installed (.ci/run installs it with apt-get)")


def _house_points(seed: int = 0, turns: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Coloured points (N, 3), (N, 3) of what the robot sees turning on the spot at the start of
    the house's first episode (80x60 depth back-projected): a map of the house as the demo starts."""
    from splatsearch import sim
    from splatsearch.camera import pixels_to_world

    house = sim.make_house(seed)
    env = sim.HouseEnv(house, width=80, height=60)
    obs = env.reset(sim.make_episodes(house, 1, "val", seed=seed, env=env)[0].start)
    pts, cols = [], []
    for _ in range(turns):
        rows, c = np.nonzero(obs.frame.depth > 0)
        pts.append(pixels_to_world(c, rows, obs.frame.depth[rows, c], obs.viewmat, env.K))
        cols.append(obs.frame.rgb[rows, c])
        obs = env.step("turn_left")
    return np.concatenate(pts).astype(np.float32), np.concatenate(cols).astype(np.float32)


@contextlib.contextmanager
def _browser(viewer):
    """Headless chromium on the viewer's URL; yields the connected clients (empty if none within
    60 s). The browser is stopped before its profile folder is removed."""
    with tempfile.TemporaryDirectory(ignore_cleanup_errors=True) as profile:
        browser = subprocess.Popen(["chromium", *CHROMIUM_FLAGS, f"--user-data-dir={profile}",
                                    "--window-size=800,600", viewer.url],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            t0 = time.time()
            while not viewer.server.get_clients() and time.time() - t0 < 60:
                time.sleep(0.2)
            yield list(viewer.server.get_clients().values())
        finally:
            browser.terminate()
            browser.wait(10)


def test_framing_camera_sees_every_point():
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(3.5, 10.7, 2000), rng.uniform(5.4, 11.2, 2000), rng.uniform(0, 2.2, 2000)]
    fov = np.deg2rad(75)
    pos, look = framing_camera(pts, fov=fov)
    assert 3.5 < look[0] < 10.7 and 5.4 < look[1] < 11.2
    fwd = (look - pos) / np.linalg.norm(look - pos)
    right = np.cross(fwd, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    cam = (pts - pos) @ np.stack([right, down, fwd], 1)
    assert (cam[:, 2] > 0).all()
    t = np.tan(fov / 2)  # a square viewport: the tighter of the two half-angles
    assert (np.abs(cam[:, 0] / cam[:, 2]) < t).mean() > 0.97 and (np.abs(cam[:, 1] / cam[:, 2]) < t).mean() > 0.97


def test_port_numbers_are_checked_before_the_server_starts():
    assert check_port(0) == 0 and check_port(65535) == 65535
    for bad in (-1, 65536, 99999, "8080", 80.5):
        with pytest.raises(ValueError, match="port"):
            check_port(bad)
    t0 = time.time()
    with pytest.raises(ValueError, match="0..65535"):
        SearchViewer(port=99999)  # used to hang forever after viser's thread died
    assert time.time() - t0 < 30


@needs_chromium
def test_default_view_of_house_0_shows_the_map():
    """What a user sees on opening the demo's URL: no camera placed by the test."""
    pts, cols = _house_points(0)
    viewer = SearchViewer(port=_free_port(), max_z=None)
    try:
        n = len(pts)
        viewer.set_map(pts, np.full((n, 3), 0.04, np.float32), np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                       np.full(n, 0.9, np.float32), cols)
        assert not np.allclose(viewer.server.initial_camera.position, (3, 3, 3))  # not viser's default
        with _browser(viewer) as clients:
            assert clients, "chromium did not connect to the viewer within 60 s"
            t0 = time.time()
            while True:  # the splats arrive in their own time on a loaded machine
                img = clients[0].camera.get_render(240, 320, timeout=60)
                drawn = np.abs(img[..., :3].astype(int) - 255).max(-1) > 30  # not the white background
                if drawn.mean() > 0.2 or time.time() - t0 > 60:
                    break
                time.sleep(1.0)
            np.testing.assert_allclose(clients[0].camera.position, viewer.server.initial_camera.position, atol=0.05)
    finally:
        viewer.close()
    assert drawn.mean() > 0.2, drawn.mean()
    rows, cols_ = np.nonzero(drawn)  # the map is framed, not pushed into a corner
    assert 60 < rows.mean() < 180 and 80 < cols_.mean() < 240


@needs_chromium
def test_splats_are_drawn_in_a_headless_browser():
    import viser.transforms as vtf

    viewer = SearchViewer(port=_free_port(), auto_frame=False)
    try:
        rng = np.random.default_rng(0)
        n = 5000
        means = np.c_[rng.uniform(-1, 1, (n, 2)), rng.uniform(-0.05, 0.05, n)].astype(np.float32)
        colors = np.tile(np.float32([1.0, 0.0, 0.0]), (n, 1))
        sent = viewer.set_map(means, np.full((n, 3), 0.03, np.float32), np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                              np.full(n, 0.9, np.float32), colors)
        assert sent == n
        occ = np.zeros((40, 40), int)
        occ[:20] = 1  # free cells at y < -1 m, below the red square
        viewer.set_occupancy(occ, (-3.0, -3.0), 0.1)
        with _browser(viewer) as clients:
            assert clients, "chromium did not connect to the viewer within 60 s"
            down = np.array([[1, 0, 0], [0, -1, 0], [0, 0, -1]], float)  # camera above, looking down
            # the scene messages arrive in their own time on a loaded machine: render until the
            # free-space plane (the last thing sent) is drawn, for up to 60 s
            t0 = time.time()
            while True:
                img = clients[0].get_render(240, 320, wxyz=vtf.SO3.from_matrix(down).wxyz, position=(0, 0, 3.0),
                                            fov=1.0, timeout=60)
                if _grey(img)[-10:, :200].mean() > 0.5 or time.time() - t0 > 60:
                    break
                time.sleep(1.0)
    finally:
        viewer.close()
    red = (img[..., 0] > 150) & (img[..., 1] < 100) & (img[..., 2] < 100)
    # the 2 m square seen from 3 m with a 1 rad vertical fov covers ~19% of the frame, centred
    assert 0.1 < red.mean() < 0.3, red.mean()
    rows, cols = np.nonzero(red)
    assert abs(rows.mean() - 120) < 15 and abs(cols.mean() - 160) < 15
    # the free-space plane (y < -1 m, x < 1 m) is drawn at the bottom of the image, not the top
    grey = _grey(img)
    assert grey[-10:, :200].mean() > 0.5 and grey[:40].mean() < 0.05


def test_map_viewer_renders_depth_and_alpha_from_a_browser_camera():
    from splatsearch.map_viewer import client_camera, render_view

    # two walls of Gaussians facing the camera: red at 2 m (left half), green at 4 m (right half)
    ys, zs = np.meshgrid(np.linspace(-1, 1, 40), np.linspace(-1, 1, 40))
    left = np.c_[np.full(1600, -1.0) + 0.9 * (ys.ravel() + 1) / 2, zs.ravel(), np.full(1600, 2.0)]
    right = np.c_[np.full(1600, 0.1) + 0.9 * (ys.ravel() + 1) / 2, zs.ravel(), np.full(1600, 4.0)]
    means = np.r_[left, right].astype(np.float32)
    n = len(means)
    colors = np.r_[np.tile([1.0, 0, 0], (1600, 1)), np.tile([0, 1.0, 0], (1600, 1))].astype(np.float32)
    g = (means, np.tile(np.float32([1, 0, 0, 0]), (n, 1)), np.full((n, 3), 0.04, np.float32),
         np.full(n, 0.95, np.float32), colors)
    # a camera at the origin looking along +z (identity orientation, OpenCV frame like viser's)
    viewmat, K = client_camera((1, 0, 0, 0), (0, 0, 0), fov=np.deg2rad(60), width=64, height=48)
    np.testing.assert_allclose(viewmat, np.eye(4), atol=1e-6)
    assert K[0, 0] == K[1, 1] and K[0, 2] == 32 and K[1, 2] == 24
    rgb = render_view(g, viewmat, K, 64, 48, "RGB")
    assert rgb[24, 16, 0] > 200 and rgb[24, 38, 1] > 200  # red left, green right
    depth = render_view(g, viewmat, K, 64, 48, "depth")
    assert not np.array_equal(depth[24, 16], depth[24, 38])  # near and far get different colours
    assert (depth[2, 32] == 0).all() or depth[24, 16].sum() > 0  # empty sky stays black
    alpha = render_view(g, viewmat, K, 64, 48, "alpha")
    assert alpha[24, 16, 0] > 200 and alpha[0, 0, 0] < alpha[24, 16, 0]
    with pytest.raises(ValueError, match="mode"):
        render_view(g, viewmat, K, 64, 48, "normals")


def test_map_viewer_panel_controls_the_splats():
    from splatsearch.gaussians import empty_map
    from splatsearch.map_viewer import MapViewer

    rng = np.random.default_rng(0)
    n = 5000
    g = empty_map(n)
    g = g.replace(means=g.means.at[:].set(np.c_[rng.uniform(0, 4, (n, 2)), rng.uniform(0, 2.5, n)].astype(np.float32)),
                  active=g.active.at[:].set(True))
    viewer = MapViewer(g, port=_free_port(), max_splats=3000)
    try:
        assert viewer.n_total == n and viewer.n_shown == 3000
        assert "3,000 of 5,000" in viewer.info.content
        viewer.budget.value = 2000
        assert viewer.n_shown == 2000
        viewer.max_z.value = 1.0  # a height cut leaves fewer than the budget
        assert viewer.n_shown == int((np.asarray(g.means)[:, 2] <= 1.0).sum()) < 2000
        viewer.mode.value = "depth"
        assert "rendered here" in viewer.info.content and viewer._splats.visible is False
        # framed on the map: above it, looking at its middle
        assert viewer.frame_pos[2] > 2.5 and 0 < viewer.frame_look[0] < 4
    finally:
        viewer.close()
    with pytest.raises(ValueError, match="no active"):
        MapViewer(empty_map(8), port=_free_port())


def test_viewer_counts_steps_as_the_cli_does(tmp_path, monkeypatch):
    """The viewer's status line and score plot count steps taken, like the progress bar and
    summary.json (they used to be one behind)."""
    import json

    import splatsearch.viewer as viewer_module
    from splatsearch.demo import DemoOptions, run_demo

    statuses, scores = [], []

    class RecordingViewer:
        url = "http://127.0.0.1:0"

        def __init__(self, **kw):
            pass

        def __getattr__(self, name):  # every layer setter: accept and ignore
            return lambda *a, **kw: None

        def set_status(self, text):
            statuses.append(text)

        def add_match_score(self, step, score):
            scores.append(step)

    monkeypatch.setattr(viewer_module, "SearchViewer", RecordingViewer)
    summary = run_demo(DemoOptions(seed=3, max_steps=3, out=str(tmp_path), hold=False))
    assert summary["steps"] == 3 == json.loads((tmp_path / "summary.json").read_text())["steps"]
    assert statuses[-1].startswith("**step 3**") and scores == [1, 2, 3]
