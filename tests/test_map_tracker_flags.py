"""``splatsearch map --tracker.FIELD``: every TrackerConfig field (but ``planar``) as a flag with its
own help, applied after the ``--track-*`` options, validated, and refused without ``--track``."""

import dataclasses

import pytest

from splatsearch.cli import build_parser, main
from splatsearch.slam import TrackerConfig
from splatsearch.tracking_args import TRACKER_FIELD_HELP, map_tracker_config


def _args(argv):
    return build_parser(["map", *argv]).parse_args(["map", *argv])


def test_every_tracker_field_but_planar_has_its_own_help():
    fields = {f.name for f in dataclasses.fields(TrackerConfig)}
    assert set(TRACKER_FIELD_HELP) == fields - {"planar"}
    text = build_parser(["map"]).format_help()  # the top-level parser; the map group is in the subparser
    sub = build_parser(["map"])._subparsers._group_actions[0].choices["map"].format_help()
    assert "--tracker.planar" not in sub and "--tracker." not in text
    assert "--tracker.f2f_along_distrust" in sub and "rotation only" in sub


def test_tracker_flags_reach_the_config_and_win_over_the_track_options():
    c = map_tracker_config(_args(["--track", "--tracker.f2f_along_sigma", "none", "--tracker.f2f_retry_depth_diff",
                                  "none", "--tracker.f2f_along_distrust", "none", "--track-gn-iters", "5",
                                  "--tracker.gn_iters", "7", "--tracker.f2f_prior", "off"]))
    assert (c.f2f_along_sigma, c.f2f_retry_depth_diff, c.f2f_along_distrust) == (None, None, None)
    assert c.gn_iters == 7 and c.f2f_prior is False
    d = TrackerConfig()
    assert (c.prior_lateral_sigma, c.f2f_rot_sigma, c.solver) == (d.prior_lateral_sigma, d.f2f_rot_sigma, d.solver)
    plain = map_tracker_config(_args(["--track"]))
    assert plain == TrackerConfig()


def test_tracker_flags_without_track_are_refused_with_the_flag_named():
    with pytest.raises(ValueError, match=r"--tracker\.f2f_along_sigma: only with --track"):
        map_tracker_config(_args(["--tracker.f2f_along_sigma", "0.002"]))
    with pytest.raises(ValueError, match=r"--track-gn-iters, --tracker\.iters: only with --track"):
        map_tracker_config(_args(["--track-gn-iters", "3", "--tracker.iters", "3"]))


def test_the_cli_refuses_before_loading_any_frame(capsys):
    assert main(["map", "--tracker.f2f_along_distrust", "3", "--out", "/nonexistent/never"]) == 2
    assert "--tracker.f2f_along_distrust: only with --track" in capsys.readouterr().err


@pytest.mark.parametrize("bad", [["--tracker.f2f_along_distrust", "0"], ["--tracker.solver", "newton"],
                                 ["--tracker.f2f_along_sigma", "-1"]])
def test_bad_tracker_values_fail_the_configs_own_checks(bad):
    with pytest.raises(ValueError):
        map_tracker_config(_args(["--track", *bad]))


@pytest.mark.parametrize("bad", [["--tracker.iters", "many"], ["--tracker.f2f_prior", "maybe"],
                                 ["--tracker.planar", "true"]])
def test_malformed_tracker_flags_are_parser_errors(bad, capsys):
    with pytest.raises(SystemExit):
        _args(["--track", *bad])
    assert "error" in capsys.readouterr().err
