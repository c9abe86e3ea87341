"""CoNVOI's query / extrapolation / re-query loop, its closed loop with the DWA, the expert, the CLI
and the viewer."""

import argparse
import socket

import numpy as np
import pytest
from splatsearch.social.convoi.pipeline import CoNVOI, CoNVOIConfig
from splatsearch.social.convoi.geometry import world_to_robot
from splatsearch.social.convoi.runner import make_world, people_gaps, run_episode
from splatsearch.social.convoi.scenarios import SCENARIOS, make_scenario
from splatsearch.social.convoi.vlm import RuleBasedVLM, VLMResult


class Failing:
    calls = 0

    def select_labels(self, image, prompt, valid, scene=None):
        Failing.calls += 1
        return VLMResult(False, error="server down", source="test")


@pytest.fixture(scope="module")
def hallway():
    scn = make_scenario("hallway", 0)
    return scn, make_world(scn, "convoi")


def test_first_update_queries_and_returns_a_right_side_path(hallway):
    scn, world = hallway
    cv = CoNVOI(RuleBasedVLM())
    ref = cv.update(0.0, scn.start, scn.peds, world)
    assert ref is not None and len(ref) == 3
    q = cv.queries[0]
    assert q.result.ok and q.context == "an indoor corridor"
    assert q.prompt.endswith("keeps close to the right wall.")
    assert (world_to_robot(ref, scn.start)[:, 1] < -0.2).all()  # keep right
    assert np.all(np.diff(world_to_robot(ref, scn.start)[:, 0]) > 0)  # row by row, ahead
    assert cv.last_marked is not None and cv.last_marked.dtype == np.uint8


def test_failed_queries_fall_back_to_plain_dwa_and_retry_later(hallway):
    scn, world = hallway
    Failing.calls = 0
    cv = CoNVOI(Failing(), cfg=CoNVOIConfig(retry_s=1.0))
    assert cv.update(0.0, scn.start, scn.peds, world) is None
    assert cv.update(0.5, scn.start, scn.peds, world) is None and Failing.calls == 1
    cv.update(1.0, scn.start, scn.peds, world)
    assert Failing.calls == 2
    st = cv.stats()
    assert st["queries"] == 2 and st["failures"] == 2


def test_latency_delays_the_reference_path(hallway):
    scn, world = hallway
    cv = CoNVOI(RuleBasedVLM(), cfg=CoNVOIConfig(latency_s=0.5))
    assert cv.update(0.0, scn.start, scn.peds, world) is None
    assert cv.update(0.3, scn.start, scn.peds, world) is None
    assert cv.update(0.5, scn.start, scn.peds, world) is not None
    assert len(cv.queries) == 1


def test_extrapolation_extends_the_path_when_the_context_is_unchanged(hallway):
    from splatsearch.social.convoi.pedsim import make_state

    scn, world = hallway
    nobody = make_state(np.zeros((0, 2)), [], [])  # an empty corridor: the context cannot change
    cv = CoNVOI(RuleBasedVLM())
    pose = np.array([1.0, -0.45, 0.0])
    cv.update(0.0, pose, nobody, world)
    first = cv.ref.copy()
    near_end = np.array([first[-1, 0] - 1.0, first[-1, 1], 0.0])  # within d_thresh of the last point
    ref = cv.update(1.5, near_end, nobody, world)
    assert cv.extrapolations == 1 and len(cv.queries) == 1
    # a changed context (people ahead) re-queries instead
    cv.update(3.0, near_end + [1.0, 0.0, 0.0], scn.peds, world)
    assert len(cv.queries) == 2 and cv.queries[-1].context != cv.queries[0].context
    new = ref[-1]
    d = first[-1] - first[-2]
    # the new point continues the fitted line by d_extend
    assert np.linalg.norm(new - first[-1]) == pytest.approx(cv.cfg.d_extend, abs=1e-6)
    u, e = d / np.linalg.norm(d), (new - first[-1]) / cv.cfg.d_extend
    assert float(u @ e) > 0.9  # the same direction as the path


def test_ground_truth_scores(hallway):
    scn, world = hallway
    cv = CoNVOI(RuleBasedVLM())
    cv.set_ground_truth(np.stack([np.linspace(0, 11, 50), np.full(50, -0.45)], -1))
    cv.update(0.0, scn.start, scn.peds, world)
    q = cv.queries[0]
    assert q.gt_robot is not None and len(q.gt_robot) == 3
    assert q.error < 0.3 and q.cosine > 0.99 and q.unacceptable is False


def test_closed_loop_convoi_keeps_right_in_the_hallway(hallway):
    scn, _ = hallway
    cv = CoNVOI(RuleBasedVLM())
    res = run_episode(scn, "convoi", convoi=cv, max_steps=45)
    assert res.robot.shape == (46, 3) and res.cmds.shape == (45, 2)
    assert res.robot[-1, 0] > 1.5  # it makes progress
    assert res.robot[-1, 1] < -0.2  # toward the right side the reference path asks for
    assert cv.stats()["queries"] >= 1 and res.wall_hits == 0


@pytest.mark.slow
@pytest.mark.parametrize("name", SCENARIOS)
def test_expert_is_a_socially_compliant_reference(name):
    scn = make_scenario(name, 0)
    res = run_episode(scn, "expert")
    assert res.reached and res.wall_hits == 0
    assert (res.robot_contacts == 0).all()
    assert people_gaps(res).min() > 0.5  # centre to centre: never touches anybody


@pytest.mark.slow
@pytest.mark.parametrize("name", SCENARIOS)
def test_dwa_and_convoi_episodes_run(name):
    scn = make_scenario(name, 0)
    d = run_episode(scn, "dwa")
    c = run_episode(scn, "convoi", convoi=CoNVOI(RuleBasedVLM()))
    assert d.reached
    assert c.convoi["queries"] >= 1
    assert d.wall_hits == 0 and c.wall_hits == 0


def test_cli_parser_and_argument_errors():
    from splatsearch.social.cli import register, run_command

    p = argparse.ArgumentParser()
    s = p.add_subparsers(dest="command")
    register(s)
    a = p.parse_args(["social", "--scenario", "hallway", "--seeds", "1"])
    assert a.func is run_command and a.scenario == "hallway" and a.seeds == 1 and not a.viewer
    b = p.parse_args(["social", "run", "--scenario", "all", "--seeds", "3", "--viewer"])
    assert b.func is run_command and b.social_command == "run" and b.seeds == 3 and b.viewer
    for bad in (["social", "--scenario", "mall"], ["social", "--seeds", "0"], ["social", "--methods", "rl"],
                ["social", "--vlm", "openai"]):
        with pytest.raises(ValueError):
            run_command(p.parse_args(bad))


@pytest.mark.slow
def test_cli_prints_the_tables(capsys):
    from splatsearch.social.cli import register

    p = argparse.ArgumentParser()
    register(p.add_subparsers(dest="command"))
    a = p.parse_args(["social", "--scenario", "hallway", "--seeds", "1"])
    assert a.func(a) == 0
    out = capsys.readouterr().out
    for word in ("MSE", "Haus", "PSV", "Fréchet", "Norm. Traj. Length", "Mean Velocity", "Cosine", "CoNVOI + DWA"):
        assert word in out


def _free_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def test_viewer_shows_a_scene_headless():
    from splatsearch.social.convoi.viewer import SocialViewer

    scn = make_scenario("static_groups", 0)
    v = SocialViewer(port=_free_port())
    try:
        assert v.url.startswith("http://127.0.0.1:")
        v.set_walls(scn.capsules)
        pos = np.asarray(scn.peds.pos)
        v.set_people(pos, np.asarray(scn.peds.active), groups=scn.groups)
        v.set_robot(scn.start)
        v.set_path("route", scn.global_path())
        v.set_rollout(np.c_[np.linspace(0, 1, 30), np.zeros(30), np.zeros(30)])
        v.set_reference([[1.0, 0.0], [2.0, -0.5]], scn.start[:2])
        v.set_marked_image(np.zeros((24, 32, 3), np.float32))
        v.set_status("test")
        active = int(np.asarray(scn.peds.active).sum())
        assert sum(h.visible for h in v._people) == active
        v.set_people(pos, np.r_[np.ones(2, bool), np.zeros(len(pos) - 2, bool)])
        assert sum(h.visible for h in v._people) == 2
    finally:
        v.close()


@pytest.mark.slow
@pytest.mark.skipif(__import__("shutil").which("chromium") is None, reason="chromium is not installed")
def test_viewer_draws_people_in_a_headless_browser():
    import subprocess
    import tempfile
    import time

    import viser.transforms as vtf

    from splatsearch.social.convoi.viewer import SocialViewer

    flags = ["--headless", "--no-sandbox", "--enable-unsafe-swiftshader", "--use-angle=swiftshader",
             "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run"]
    v = SocialViewer(port=_free_port())
    browser = None
    try:
        v.set_people(np.array([[0.0, 0.0], [50.0, 50.0]]), np.array([True, False]))  # one person at the origin
        with tempfile.TemporaryDirectory() as profile:
            browser = subprocess.Popen(["chromium", *flags, f"--user-data-dir={profile}", "--window-size=800,600",
                                        v.url], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            t0 = time.time()
            while not v.server.get_clients() and time.time() - t0 < 60:
                time.sleep(0.2)
            clients = list(v.server.get_clients().values())
            assert clients, "chromium did not connect to the viewer within 60 s"
            time.sleep(2.0)
            down = np.array([[1, 0, 0], [0, -1, 0], [0, 0, -1]], float)
            img = clients[0].get_render(240, 320, wxyz=vtf.SO3.from_matrix(down).wxyz, position=(0, 0, 5.0),
                                        fov=1.0, timeout=60)
    finally:
        if browser is not None:
            browser.terminate()
            browser.wait(10)
        v.close()
    orange = (img[..., 0] > 150) & (img[..., 1] > 80) & (img[..., 1] < 200) & (img[..., 2] < 110)
    assert orange.mean() > 0.002, orange.mean()  # the person's cylinder is drawn ...
    rows, cols = np.nonzero(orange)
    assert abs(rows.mean() - 120) < 20 and abs(cols.mean() - 160) < 20  # ... where the person stands
