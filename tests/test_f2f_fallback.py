"""TrackerConfig.f2f_fallback_window / f2f_fallback_fail: while OpenCV fails on more than a share of
the last links, accepted links give the rotation prior only (opt-in)."""

import numpy as np
import pytest

from splatsearch import slam as slam_mod
from splatsearch.mapper import MapperConfig
from splatsearch.slam import SLAM, TrackerConfig


def _untrusted_after(monkeypatch, outcomes, **cfg):
    """Feed links with the given outcomes ("A" accepted, "F" failed, "R" rejected), each its own
    processed frame; per link, whether the chain was marked untrusted."""
    seq = iter(outcomes)
    cur = {}

    def fake_step(*a, **k):
        cur["o"] = next(seq)
        return None if cur["o"] == "F" else np.eye(4)

    monkeypatch.setattr(slam_mod.odometry_f2f, "f2f_step", fake_step)
    monkeypatch.setattr(slam_mod.odometry_f2f, "gate_step", lambda *a, **k: cur["o"] == "A")
    s = SLAM(np.array([[50.0, 0, 16], [0, 50.0, 12], [0, 0, 1]]), 32, 24, MapperConfig(),
             TrackerConfig(f2f_retry_depth_diff=None, f2f_along_distrust=None, **cfg))
    rgb, depth, odo = np.zeros((24, 32, 3), np.float32), np.ones((24, 32), np.float32), np.eye(4)
    out = []
    for _ in outcomes:
        s._f2f_reset(rgb, depth, odo)
        s._f2f_link_to(rgb, depth, odo)
        out.append(s._f2f_untrusted)
    return out


def test_off_by_default_and_validated():
    assert TrackerConfig().f2f_fallback_window is None
    for bad in (dict(f2f_fallback_window=0), dict(f2f_fallback_fail=1.0), dict(f2f_fallback_fail=-0.1)):
        with pytest.raises(ValueError, match="f2f_fallback"):
            TrackerConfig(**bad).validate()


def test_accepted_links_fall_back_while_the_window_fails_often(monkeypatch):
    # window 4, more than half failed: needs 3 failed among the last 4 links (this accepted one included)
    got = _untrusted_after(monkeypatch, "FFAFA" + "AAAA" + "FFFA", f2f_fallback_window=4, f2f_fallback_fail=0.5)
    # link by link: accepted, and more than 2 of the last 4 links (itself included) failed
    want, hist = [], []
    for o in "FFAFA" + "AAAA" + "FFFA":
        hist.append(o == "F")
        want.append(o == "A" and sum(hist[-4:]) > 2)
    assert got == want and any(want)
    assert got[-1] and sum(got) == 1  # only the A after F F F (F A F A has 2 of 4)
    # rejected links are not failures
    assert not any(_untrusted_after(monkeypatch, "RRRA", f2f_fallback_window=4, f2f_fallback_fail=0.5))
    # links not yet made count as not failed: 2 failed of a window of 10 is not more than 0.35
    assert not any(_untrusted_after(monkeypatch, "FFA", f2f_fallback_window=10, f2f_fallback_fail=0.35))
    assert not any(_untrusted_after(monkeypatch, "FFFAFFFA"))  # off: never
