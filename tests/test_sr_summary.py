"""benchmarks/sr_summary.py: counts over the common episodes, paired wins and the sign test."""

import json
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))

import sr_summary  # noqa: E402


def _row(house, ep, variant, success, spl=0.5, wall=10.0):
    return {"house_seed": house, "episode_id": ep, "variant": variant, "success": success,
            "spl": spl if success else 0.0, "wall_time": wall}


def test_summary_counts_only_episodes_every_variant_finished(tmp_path):
    rows = [_row(1000, 0, "a", True), _row(1000, 0, "b", False),
            _row(1000, 1, "a", True), _row(1000, 1, "b", True),
            _row(1000, 2, "a", False)]  # episode 2 has no "b" run yet: left out
    path = tmp_path / "results.json"
    path.write_text(json.dumps(rows))
    s = sr_summary.summarise(sr_summary.load_rows(path), ["a", "b"])
    assert s["episodes"] == 2
    assert s["variants"]["a"]["sr"] == 1.0 and s["variants"]["b"]["sr"] == 0.5
    assert s["variants"]["a"]["spl"] == 0.5 and s["variants"]["b"]["spl"] == 0.25
    pair = s["pairs"]["a vs b"]
    assert (pair["wins"], pair["ties"], pair["losses"]) == (1, 1, 0)
    assert pair["sr_step"] == 0.5


def test_sign_test_matches_the_binomial():
    assert sr_summary.sign_test_p(0, 0) == 1.0
    assert abs(sr_summary.sign_test_p(5, 0) - 2 * 0.5**5) < 1e-12
    assert sr_summary.sign_test_p(5, 4) == 1.0
    assert abs(sr_summary.sign_test_p(6, 0) - 0.03125) < 1e-12
