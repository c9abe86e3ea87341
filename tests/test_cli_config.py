"""Every MapperConfig / AgentConfig field is a documented CLI flag; only given flags change a config."""

import argparse
import dataclasses

import pytest

from splatsearch.cli import CONFIG_FLAGS, build_parser
from splatsearch.cli_config import add_config_flags, apply_overrides, config_overrides, field_help


def _flags(parser, command):
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[command]
    return {s: a for a in sub._actions for s in a.option_strings}


def _leaves(cls, prefix, skip=()):
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        if dataclasses.is_dataclass(default):
            yield from _leaves(type(default), f"{prefix}.{f.name}")
        else:
            yield f"--{prefix}.{f.name}"


@pytest.mark.parametrize("command", sorted(CONFIG_FLAGS))
def test_every_config_field_is_a_flag_with_type_and_default(command):
    import importlib

    flags = _flags(build_parser([command]), command)
    for prefix, path, skip, _ in CONFIG_FLAGS[command]:
        module, _, name = path.partition(":")
        cls = getattr(importlib.import_module(module), name)
        want = set(_leaves(cls, prefix, skip))
        assert want and want <= set(flags)
        for flag in want:
            assert "(default: " in flags[flag].help, (flag, flags[flag].help)
        assert not any(f.startswith(f"--{prefix}.") for f in _flags(build_parser([]), command))


def test_field_help_reads_the_class_docstring():
    from splatsearch.agent.config import AgentConfig
    from splatsearch.search.local_map import LocalMapConfig

    assert "merge distance" in field_help(AgentConfig, "tau_d")
    assert "Metres of surroundings" in field_help(LocalMapConfig, "margin")
    assert field_help(AgentConfig, "no_such_field") == ""


def test_only_given_flags_change_the_config():
    from splatsearch.agent.config import AgentConfig

    p = argparse.ArgumentParser()
    add_config_flags(p, AgentConfig, "agent", skip=("variant",))
    args = p.parse_args(["--agent.tau_m", "20", "--agent.colour_cue", "off", "--agent.view_elevations_deg", "10,30",
                         "--agent.local_map.stride", "3"])
    ov = config_overrides(args, "agent")
    assert ov == {"tau_m": 20.0, "colour_cue": False, "view_elevations_deg": (10, 30), "local_map": {"stride": 3}}
    cfg = apply_overrides(AgentConfig(), ov)
    assert cfg.tau_m == 20.0 and cfg.colour_cue is False and cfg.local_map.stride == 3
    assert cfg.n_views == AgentConfig().n_views and cfg.local_map.margin == AgentConfig().local_map.margin
    with pytest.raises(SystemExit):
        p.parse_args(["--agent.colour_cue", "maybe"])
    assert config_overrides(p.parse_args([]), "agent") == {}


def test_map_flags_reach_the_mapper_config_and_are_checked():
    from splatsearch.mapper import MapperConfig

    p = argparse.ArgumentParser()
    add_config_flags(p, MapperConfig, "mapper")
    ov = config_overrides(p.parse_args(["--mapper.lr", '{"means": 2e-3, "log_scales": 5e-3, "quats": 1e-3, '
                                        '"opacity_logits": 5e-2, "colors": 5e-3}', "--mapper.first_iters", "none"]),
                          "mapper")
    cfg = apply_overrides(MapperConfig(), ov)
    assert cfg.lr["means"] == 2e-3 and cfg.first_iters is None
    with pytest.raises(ValueError):
        apply_overrides(MapperConfig(), {"window_select": "nonsense"})


def test_every_config_field_is_documented_in_its_class():
    from splatsearch.agent.config import AgentConfig
    from splatsearch.mapper import MapperConfig
    from splatsearch.search.local_map import LocalMapConfig

    for cls, skip in ((MapperConfig, ()), (AgentConfig, ("variant",)), (LocalMapConfig, ())):
        bare = [f.name for f in dataclasses.fields(cls) if f.name not in skip and not field_help(cls, f.name)]
        assert bare == [], (cls.__name__, bare)
