"""``splatsearch map --preset``: 'fast' keeps the old per-frame budget, 'quality' is the real-sensor
benchmark's recipe (``benchmarks/slam_eval.py`` REAL + REAL_REFINE), and explicit flags win."""

import pytest

from splatsearch.cli import MAP_PRESETS, build_parser, map_mapper_config, resolve_map_preset


def _args(argv):
    return build_parser(["map", *argv]).parse_args(["map", *argv])


def test_fast_is_the_default_and_keeps_the_old_budget():
    a = resolve_map_preset(_args([]))
    assert (a.iters, a.first_iters, a.stride, a.keyframe_every, a.refine) == (15, None, 3, 5, 0)
    c = map_mapper_config(_args([]), real=True)
    assert c.iters == 15 and c.stride == 3 and c.keyframe_every == 5 and c.pixel_scale == 3.0


def test_quality_matches_the_benchmark_recipe():
    import importlib.util
    import pathlib

    path = pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "slam_eval.py"
    spec = importlib.util.spec_from_file_location("slam_eval_for_test", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    c = map_mapper_config(_args(["--preset", "quality"]), real=True)
    for key, val in bench.REAL.items():
        assert getattr(c, key) == val, key
    assert MAP_PRESETS["quality"]["refine"] == bench.REAL_REFINE


def test_explicit_flags_win_over_the_preset():
    a = resolve_map_preset(_args(["--preset", "quality", "--iters", "7", "--refine", "0"]))
    assert (a.iters, a.refine, a.first_iters, a.keyframe_every) == (7, 0, 60, 1)
    assert resolve_map_preset(a) is a and a.iters == 7  # idempotent


@pytest.mark.parametrize("bad", [["--preset", "best"], ["--iters", "0"], ["--stride", "-1"]])
def test_bad_values_are_refused(bad, capsys):
    with pytest.raises(SystemExit):
        _args(bad)
    assert "error" in capsys.readouterr().err


def test_odometry_pose_refinement_takes_the_small_translation_step():
    """With --odometry the simulator recipe's 2e-5 m refinement step is the default; a
    --mapper.pose_lr_trans override still wins; without odometry the MapperConfig default stays."""
    from splatsearch.cli import SIM_ODOMETRY_POSE_LR_TRANS
    from splatsearch.cli_config import apply_overrides, config_overrides
    from splatsearch.mapper import MapperConfig

    sim = _args(["--track", "--odometry", "--pose-refine"])
    assert map_mapper_config(sim, real=False).pose_lr_trans == SIM_ODOMETRY_POSE_LR_TRANS == 2e-5
    plain = map_mapper_config(_args(["--track", "--pose-refine"]), real=False)
    assert plain.pose_lr_trans == MapperConfig().pose_lr_trans
    told = _args(["--track", "--odometry", "--pose-refine", "--mapper.pose_lr_trans", "1e-4"])
    c = apply_overrides(map_mapper_config(told, real=False), config_overrides(told, "mapper"))
    assert c.pose_lr_trans == 1e-4
