"""``splatsearch map`` fits a per-frame exposure by default on datasets (real, auto-exposed cameras)
and not on simulator walks; ``--exposure`` / ``--no-exposure`` override either."""

import pytest

from splatsearch.cli import build_parser, map_mapper_config


def _cfg(argv, real):
    args = build_parser(["map", *argv]).parse_args(["map", *argv])
    return map_mapper_config(args, real)


@pytest.mark.parametrize("argv, real, want", [
    ([], True, True), ([], False, False),
    (["--no-exposure"], True, False), (["--exposure"], False, True), (["--exposure"], True, True),
])
def test_exposure_default_follows_the_data(argv, real, want):
    assert _cfg(argv, real).exposure is want


def test_real_data_keeps_its_sensor_settings():
    c = _cfg([], True)
    assert c.fill_holes and c.lambda_g == 0.3 and c.lr["means"] == 2e-4
    s = _cfg([], False)
    assert not s.fill_holes and not s.exposure
