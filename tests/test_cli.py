"""The command-line entry points, run in-process on small inputs."""

import json

from splatsearch import sim
from splatsearch.cli import main


def test_sim_preview_episodes_export(tmp_path):
    assert main(["sim", "preview", "--seed", "2", "--out", str(tmp_path / "prev")]) == 0
    assert (tmp_path / "prev" / "house_map.png").stat().st_size > 1000
    assert (tmp_path / "prev" / "house_frames.png").stat().st_size > 1000
    ep = tmp_path / "eps.json"
    assert main(["sim", "episodes", "--seed", "2", "--n", "2", "--split", "val-hard", "--out", str(ep)]) == 0
    eps = sim.load_episodes(str(ep))
    assert len(eps) == 2 and all(e.split == "val-hard" for e in eps)
    glb = tmp_path / "h.glb"
    assert main(["sim", "export", "--seed", "2", "--out", str(glb)]) == 0
    assert len(sim.load_house(str(glb)).faces) == len(sim.make_house(2).faces)


def test_bad_arguments_exit_with_code_2(tmp_path, capsys):
    assert main(["sim", "preview", "--rooms", "0", "--out", str(tmp_path)]) == 2
    assert "n_rooms" in capsys.readouterr().err


def test_map_command_writes_map_and_summary(tmp_path):
    out = tmp_path / "map"
    rc = main(["map", "--seed", "1", "--frames", "5", "--width", "64", "--height", "48", "--iters", "3",
               "--holdout-every", "4", "--out", str(out)])
    assert rc == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames_mapped"] == 4 and summary["held_out"]["n"] == 1
    assert summary["train"]["psnr"] > 10
    assert summary["train"]["psnr_valid"] > 10  # the sim renders depth almost everywhere
    assert (out / "map.ply").stat().st_size > 100 and (out / "map.npz").exists()


def test_bench_small_scene(capsys):
    assert main(["bench", "--scene", "small", "--repeats", "1"]) == 0
    assert "random 10k" in capsys.readouterr().out


def test_demo_headless_writes_run_folder_and_export_round_trips(tmp_path):
    from splatsearch import io

    out = tmp_path / "demo"
    assert main(["demo", "--no-viewer", "--seed", "3", "--max-steps", "4", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 4 and summary["interrupted"] is False and "success" in summary
    assert json.loads((out / "episode.json").read_text())["house_seed"] == 3
    assert len(json.loads((out / "trajectory.json").read_text())) == 4
    ply = out / "map.ply"
    assert summary["gaussians"] == io.load_ply(str(ply)).n_active > 0
    npz = tmp_path / "m.npz"
    assert main(["export", str(ply), str(npz)]) == 0
    assert main(["export", str(npz), str(tmp_path / "back.ply")]) == 0
    assert io.load_ply(str(tmp_path / "back.ply")).n_active == summary["gaussians"]
    assert main(["export", str(ply), str(tmp_path / "m.txt")]) == 2
    assert main(["demo", "--no-viewer", "--seed", "-1", "--out", str(out)]) == 2


def _options(parser, path=()):
    import argparse

    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            for name, sub in a.choices.items():
                yield from _options(sub, (*path, name))
        elif not isinstance(a, argparse._HelpAction):
            yield " ".join(path), a


def test_every_flag_has_help_with_its_default():
    import argparse

    from splatsearch.cli import build_parser

    parser = build_parser()
    opts = list(_options(parser))
    assert len(opts) > 80 and {p for p, _ in opts} >= {"map", "eval", "demo", "social train", "social eval"}
    bare = [(p, a.option_strings or a.dest) for p, a in opts if not (a.help or "").strip()]
    assert bare == []
    formatter = parser._subparsers._group_actions[0].choices["map"]._get_formatter()
    for path, a in opts:
        if a.option_strings and not isinstance(a, argparse._VersionAction):
            text = formatter._get_help_string(a)
            assert "default" in text, (path, a.option_strings, text)


def test_building_the_parser_imports_neither_jax_nor_warp():
    import subprocess
    import sys

    code = ("import sys, splatsearch.cli as c; c.build_parser(); "
            "print(sorted(m for m in ('jax', 'warp', 'flax', 'cv2') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def _one_line_error(capsys, needle: str) -> str:
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    assert err.startswith("splatsearch: error:") and needle in err, err
    return err


def test_bad_port_is_refused_at_once(capsys):
    import pytest

    for cmd in (["demo", "--no-viewer"], ["view", "map.ply"]):
        with pytest.raises(SystemExit) as e:
            main([*cmd, "--port", "99999"])
        assert e.value.code == 2
        assert "port must be in 0..65535" in capsys.readouterr().err


def test_missing_or_wrong_paths_are_one_line_errors(tmp_path, capsys):
    assert main(["view", "/nonexistent.ply"]) == 2
    _one_line_error(capsys, "/nonexistent.ply")
    assert main(["view", str(tmp_path)]) == 2
    _one_line_error(capsys, str(tmp_path))
    assert main(["export", "/nonexistent.npz", str(tmp_path / "x.ply")]) == 2
    _one_line_error(capsys, "/nonexistent.npz")
    assert main(["map", "--tum", str(tmp_path / "missing"), "--out", str(tmp_path / "m")]) == 2
    _one_line_error(capsys, "missing")
    assert main(["map", "--tum", str(tmp_path), "--out", str(tmp_path / "m")]) == 2  # a folder without TUM files
    _one_line_error(capsys, str(tmp_path))


def test_eval_rejects_zero_episodes_in_user_terms(capsys):
    import pytest

    with pytest.raises(SystemExit) as e:
        main(["eval", "--episodes", "0"])
    assert e.value.code == 2 and "--episodes: must be >= 1" in capsys.readouterr().err


def test_atomic_writes_respect_the_umask(tmp_path):
    import os
    import stat

    from splatsearch import io

    old = os.umask(0o027)
    try:
        io.atomic_write_bytes(str(tmp_path / "a.json"), b"{}")
        assert stat.S_IMODE((tmp_path / "a.json").stat().st_mode) == 0o640
        os.umask(0o022)
        io.atomic_write_bytes(str(tmp_path / "b.json"), b"{}")
        assert stat.S_IMODE((tmp_path / "b.json").stat().st_mode) == 0o644
        assert not [p for p in tmp_path.iterdir() if p.name.startswith(".tmp-")]
    finally:
        os.umask(old)


def test_demo_run_folder_is_shareable_and_its_summary_has_one_key_per_fact(tmp_path, monkeypatch):
    import os
    import stat

    from splatsearch import demo, episode

    old = os.umask(0o022)
    try:
        out = tmp_path / "run"
        assert main(["demo", "--no-viewer", "--seed", "3", "--max-steps", "3", "--out", str(out)]) == 0
        modes = {p.name: stat.S_IMODE(p.stat().st_mode) for p in out.iterdir()}
        assert set(modes) >= {"goal.png", "map.ply", "trajectory.json", "episode.json", "summary.json"}
        assert set(modes.values()) == {0o644}, modes
        summary = json.loads((out / "summary.json").read_text())
        assert tuple(summary) == demo.SUMMARY_KEYS
        assert summary["steps"] == 3 and summary["success"] in (True, False) and summary["reason"] is None

        # an interrupted run: the episode is never judged, so its outcome fields are null with the reason
        real = episode.run_episode

        def interrupted(ep, config=None, *, on_step=None, **kw):
            def stop_after_two(agent, obs, info):
                on_step(agent, obs, info)
                if obs.step >= 1:
                    raise KeyboardInterrupt
            return real(ep, config, on_step=stop_after_two, **kw)

        monkeypatch.setattr(episode, "run_episode", interrupted)
        out2 = tmp_path / "run2"
        assert main(["demo", "--no-viewer", "--seed", "3", "--max-steps", "6", "--out", str(out2)]) == 0
        s2 = json.loads((out2 / "summary.json").read_text())
        assert tuple(s2) == demo.SUMMARY_KEYS and s2["interrupted"] is True
        assert s2["success"] is None and s2["spl"] is None and "interrupted" in s2["reason"]
        assert s2["steps"] == 2 and (out2 / "map.ply").exists()
    finally:
        os.umask(old)


def test_version_has_one_source(capsys):
    import importlib.metadata
    import os

    import pytest

    import splatsearch

    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"splatsearch {splatsearch.__version__}"
    assert importlib.metadata.version("splatsearch") == splatsearch.__version__
    assert os.path.exists(os.path.join(os.path.dirname(splatsearch.__file__), "py.typed"))


def test_every_imported_third_party_package_is_declared():
    """scipy, plyfile and httpx are imported by the library, so the distribution must require them."""
    import importlib.metadata
    import re

    declared = {re.split(r"[<>=!~\[; ]", r, 1)[0].lower() for r in importlib.metadata.requires("splatsearch") or []
                if "extra ==" not in r}
    assert {"scipy", "plyfile", "httpx", "jax", "warp-lang", "opencv-python-headless", "viser"} <= declared
