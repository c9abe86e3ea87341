"""TrackerConfig.f2f_along_distrust: after a run of non-accepted frame-to-frame links the next
accepted ones are kept from the along-path prior (default 2 since stop 46, rule J)."""

import numpy as np
import pytest

from splatsearch import slam as slam_mod
from splatsearch.mapper import MapperConfig
from splatsearch.slam import SLAM, TrackerConfig


def _untrusted_after(monkeypatch, outcomes, distrust):
    """Feed links with the given outcomes ("A" accepted, "F" failed, "R" rejected); per link,
    whether the chain was marked untrusted."""
    step = np.eye(4)
    seq = iter(outcomes)
    cur = {}

    def fake_step(*a, **k):
        cur["o"] = next(seq)
        return None if cur["o"] == "F" else step

    monkeypatch.setattr(slam_mod.odometry_f2f, "f2f_step", fake_step)
    monkeypatch.setattr(slam_mod.odometry_f2f, "gate_step", lambda *a, **k: cur["o"] == "A")
    s = SLAM(np.array([[50.0, 0, 16], [0, 50.0, 12], [0, 0, 1]]), 32, 24, MapperConfig(),
             TrackerConfig(f2f_along_distrust=distrust, f2f_retry_depth_diff=None))
    rgb, depth, odo = np.zeros((24, 32, 3), np.float32), np.ones((24, 32), np.float32), np.eye(4)
    out = []
    for _ in outcomes:
        s._f2f_reset(rgb, depth, odo)  # each link its own processed frame
        s._f2f_link_to(rgb, depth, odo)
        out.append(s._f2f_untrusted)
    return out


def test_default_and_validation():
    assert TrackerConfig().f2f_along_distrust == 2  # the default since stop 46 (rule J)
    with pytest.raises(ValueError, match="f2f_along_distrust"):
        TrackerConfig(f2f_along_distrust=0).validate()


def test_accepted_links_after_a_run_are_distrusted(monkeypatch):
    assert slam_mod.F2F_DISTRUST_RUN == 3
    got = _untrusted_after(monkeypatch, "FFFAAAA" + "RFAA" + "RRFAA", 2)
    assert got == [False, False, False, True, True, False, False,  # a run of 3: the next 2 accepted
                   False, False, False, False,  # a run of 2 only: trusted
                   False, False, False, True, True]
    assert not any(_untrusted_after(monkeypatch, "FFFAAAA", None))  # off: never
