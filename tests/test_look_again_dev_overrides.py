"""``benchmarks/look_again_dev.py``'s ``--agent FIELD=VALUE`` overrides, nested fields included
(issue 23, stop 48: the local-map candidate was run as ``--agent local_map.iters_per_frame=0``)."""

import os
import sys

import pytest

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))

from look_again_dev import agent_config, parse_agent_overrides  # noqa: E402

from splatsearch.agent import AgentConfig  # noqa: E402
from splatsearch.search.local_map import LocalMapConfig  # noqa: E402


def test_flat_overrides_build_the_same_config_as_before():
    o = parse_agent_overrides(["confirm_below=18", "look_again_after_refute=1", "confirm_by=rivals"])
    assert agent_config(1, o) == AgentConfig(variant="splatsearch", colour_cue=False, look_again=1, confirm_below=18,
                                             look_again_after_refute=1, confirm_by="rivals")


def test_dotted_overrides_set_the_nested_local_map_and_keep_its_other_fields():
    o = parse_agent_overrides(["confirm_below=18", "local_map.iters_per_frame=0", "local_map.refine_iters=16"])
    cfg = agent_config(1, o)
    assert cfg.confirm_below == 18
    assert cfg.local_map == LocalMapConfig(iters_per_frame=0, refine_iters=16)
    assert cfg.local_map.stride == LocalMapConfig().stride


def test_a_bad_nested_value_is_refused():
    with pytest.raises(ValueError):
        agent_config(1, parse_agent_overrides(["local_map.refine_iters=-1"]))
