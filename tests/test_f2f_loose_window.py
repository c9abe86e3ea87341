"""TrackerConfig.f2f_loose_window / f2f_loose_fail: frames are marked loose (the mapper's
pose_lr_trans_loose) while OpenCV failed on more than a share of the last links, instead of by
their own link's status (opt-in)."""

import numpy as np
import pytest

from splatsearch import slam as slam_mod
from splatsearch.mapper import MapperConfig
from splatsearch.slam import SLAM, TrackerConfig


def _loose_after(monkeypatch, outcomes, **cfg):
    """Feed links ("A" accepted, "F" failed, "R" rejected), each its own processed frame; per link,
    whether that frame would be mapped as loose."""
    seq = iter(outcomes)
    cur = {}

    def fake_step(*a, **k):
        cur["o"] = next(seq)
        return None if cur["o"] == "F" else np.eye(4)

    monkeypatch.setattr(slam_mod.odometry_f2f, "f2f_step", fake_step)
    monkeypatch.setattr(slam_mod.odometry_f2f, "gate_step", lambda *a, **k: cur["o"] == "A")
    s = SLAM(np.array([[50.0, 0, 16], [0, 50.0, 12], [0, 0, 1]]), 32, 24, MapperConfig(),
             TrackerConfig(f2f_retry_depth_diff=None, **cfg))
    rgb, depth, odo = np.zeros((24, 32, 3), np.float32), np.ones((24, 32), np.float32), np.eye(4)
    out = []
    for _ in outcomes:
        s._f2f_reset(rgb, depth, odo)
        s._f2f_link = None
        s._f2f_status = s._f2f_link_to(rgb, depth, odo)
        out.append(s._loose())
    return out


def test_off_by_default_and_validated():
    assert TrackerConfig().f2f_loose_window is None
    for bad in (dict(f2f_loose_window=0), dict(f2f_loose_fail=1.0), dict(f2f_loose_fail=-0.1)):
        with pytest.raises(ValueError, match="f2f_loose"):
            TrackerConfig(**bad).validate()


def test_off_marks_a_frame_by_its_own_link(monkeypatch):
    assert _loose_after(monkeypatch, "AFRA") == [False, True, True, False]


def test_window_marks_every_frame_while_the_recent_links_fail_often(monkeypatch):
    links = "AFFFAAAARAAA"
    got = _loose_after(monkeypatch, links, f2f_loose_window=4, f2f_loose_fail=0.5)
    want, hist = [], []
    for o in links:
        hist.append(o == "F")
        want.append(sum(hist[-4:]) > 2)  # more than half of the last 4 links (this one included) failed
    assert got == want
    # accepted frames inside the stretch are marked, a lone failed or rejected one is not
    assert got[4] and links[4] == "A" and not got[1] and not got[8]
    # not-yet-made links count as not failed: 2 failed of a window of 10 is not more than 0.25
    assert not any(_loose_after(monkeypatch, "FF", f2f_loose_window=10, f2f_loose_fail=0.25))


def test_latch_keeps_marking_after_the_window_fired(monkeypatch):
    links = "AFFFAAAARAAA"
    plain = _loose_after(monkeypatch, links, f2f_loose_window=4, f2f_loose_fail=0.5)
    latched = _loose_after(monkeypatch, links, f2f_loose_window=4, f2f_loose_fail=0.5, f2f_loose_latch=True)
    first = plain.index(True)
    assert latched == [False] * first + [True] * (len(links) - first)
    # never fired: the latch marks nothing
    assert not any(_loose_after(monkeypatch, "AFAFAA", f2f_loose_window=4, f2f_loose_fail=0.5, f2f_loose_latch=True))
