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
    from splatsearch.cli import build_parser

    parser = build_parser()
    opts = list(_options(parser))
    assert len(opts) > 80 and {p for p, _ in opts} >= {"map", "eval", "demo", "social train", "social eval"}
    bare = [(p, a.option_strings or a.dest) for p, a in opts if not (a.help or "").strip()]
    assert bare == []
    formatter = parser._subparsers._group_actions[0].choices["map"]._get_formatter()
    for path, a in opts:
        if a.option_strings:
            text = formatter._get_help_string(a)
            assert "default" in text, (path, a.option_strings, text)


def test_building_the_parser_imports_neither_jax_nor_warp():
    import subprocess
    import sys

    code = ("import sys, splatsearch.cli as c; c.build_parser(); "
            "print(sorted(m for m in ('jax', 'warp', 'flax', 'cv2') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr
