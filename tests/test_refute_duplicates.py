"""A confirm trip's refusal and duplicate DB entries of the same object (issue 23, stop 47):
``AgentConfig.refute_radius``."""

import numpy as np
import pytest

from splatsearch.agent import AgentConfig
from splatsearch.agent.config import resolve_variant
from splatsearch.agent.decision import SearchPolicy
from splatsearch.search.objects import ObjectDB


class _Verifier:
    """Feature matches alone: an entry is the goal once it passed tau_m."""

    colour_cue = False

    def is_goal(self, e):
        return e.matched

    def can_decide(self, e):
        return True


def _policy(refute_radius: float):
    cfg = AgentConfig(colour_cue=False, confirm_below=18.0, refute_radius=refute_radius)
    db = ObjectDB(tau_d=cfg.tau_d)
    pose = np.array([0.0, 0.0, 0.0])
    a = db.add("chair", [2.0, 0.0, 0.4], pose).entry_id
    # the same chair seen again from far: made more than tau_d away, its centroid then drifted to 0.6 m
    b = db.add("chair", [3.2, 0.0, 0.4], pose).entry_id
    db[b].centroid = np.array([2.6, 0.0, 0.4])
    far = db.add("chair", [6.0, 0.0, 0.4], pose).entry_id  # another chair, 4 m away
    sofa = db.add("sofa", [2.3, 0.0, 0.4], pose).entry_id  # another class, 0.3 m away
    for eid in (a, b, far, sofa):
        db.record_match(eid, 16.0, 0, cfg.tau_m)  # all marginal matches, in [tau_m, confirm_below)
    pol = SearchPolicy(cfg, resolve_variant(cfg), db, _Verifier(), explorer=None, crop_cosine={})
    pol.refuted[a] = 11.0  # a confirm trip refuted entry a: its new frame gave 11
    return pol, db, (a, b, far, sofa)


def test_default_radius_is_tau_d():
    # stop 48: the dev rule of stop 47 passed; the radius is the DB's own merge distance
    assert AgentConfig().refute_radius == 1.0 == AgentConfig().tau_d


def test_radius_0_a_refusal_covers_only_its_own_entry():
    pol, db, (a, b, far, sofa) = _policy(0.0)
    assert pol.is_refuted(db[a]) and not pol.is_refuted(db[b])
    assert [e.id for e in pol.goal_candidates()] == [b, far, sofa]
    assert pol._object_scores()[b].e_max == 16.0


def test_a_refusal_covers_a_same_class_duplicate_within_the_radius():
    pol, db, (a, b, far, sofa) = _policy(1.0)
    assert pol.refuted_by(db[b]) == a and pol.is_refuted(db[b])
    # another chair beyond the radius and another class nearby stay candidates
    assert pol.refuted_by(db[far]) is None and pol.refuted_by(db[sofa]) is None
    assert [e.id for e in pol.goal_candidates()] == [far, sofa]
    assert not pol.needs_confirm(db[b])  # covered: no trip of its own
    # in eq 20 the duplicate counts with the refusing frame's count, as the refuted entry does
    scores = pol._object_scores()
    assert scores[a].e_max == 11.0 and scores[b].e_max == 11.0 and scores[far].e_max == 16.0


def test_a_clear_pass_lifts_the_cover():
    pol, db, (a, b, far, sofa) = _policy(1.0)
    db.record_match(b, 25.0, 0, pol.cfg.tau_m)  # the duplicate itself passes clearly
    assert not pol.is_refuted(db[b]) and pol.goal_candidates()[0].id == b
    pol, db, (a, b, far, sofa) = _policy(1.0)
    db.record_match(a, 25.0, 0, pol.cfg.tau_m)  # the refuted entry passes clearly: its refusal is lifted
    assert not pol.is_refuted(db[a]) and not pol.is_refuted(db[b])


def test_refute_radius_is_checked():
    with pytest.raises(ValueError, match="refute_radius"):
        AgentConfig(refute_radius=-1.0)
    with pytest.raises(ValueError, match="refute_radius"):
        AgentConfig(refute_radius=float("nan"))


def test_refute_radius_cli_flag_has_help():
    import argparse

    from splatsearch.cli_config import add_config_flags, config_overrides

    ap = argparse.ArgumentParser()
    add_config_flags(ap, AgentConfig, "agent")
    args = ap.parse_args(["--agent.refute_radius", "1.0"])
    assert config_overrides(args, "agent") == {"refute_radius": 1.0}
    helps = {a.dest: a.help for a in ap._actions}
    assert "duplicate" in helps["agent.refute_radius"]
