"""Read the state of a running OLiVia-Nav episode from outside its loop (dev-seed oracle benchmarks).

The oracle benchmarks (``olivia_oracle_selection.py``, ``olivia_oracle_dt.py``,
``olivia_oracle_image.py``) fork the reference walker or the captioner from the robot's state at
every plan. The planner's ``plan`` sees only the observation, so the planner module's
``observe``, ``step_unicycle`` and ``pedsim`` are wrapped (in this process only) to record the
robot's pose, its last command, the pedestrians and the step; the episode loop itself is the
library's, unchanged. Only for development seeds.
"""
from __future__ import annotations

import types

import numpy as np

from splatsearch.social.convoi import pedsim
from splatsearch.social.olivia import planner as pm

_STATE: dict = {}
_INSTALLED = False


def install() -> dict:
    """Wrap the planner module's hooks (once per process) and return the shared state dict:
    ``pose`` (3,) world (x, y, yaw) at the last observation, ``cmd`` (2,) the last unicycle
    command (v m/s, w rad/s), ``peds`` the pedestrian state after the last simulator step and
    ``t`` the number of simulator steps (0.1 s each) taken so far."""
    global _INSTALLED
    if _INSTALLED:
        return _STATE
    orig_observe, orig_unicycle = pm.observe, pm.step_unicycle

    def observe(scn, pose, people, prev_pose, prev_people, path=None):
        _STATE["pose"] = np.asarray(pose)
        return orig_observe(scn, pose, people, prev_pose, prev_people, path)

    def step_unicycle(pose, cmd, dt):
        _STATE["cmd"] = np.asarray(cmd)
        return orig_unicycle(pose, cmd, dt)

    def step(peds, *a, **k):
        new, info = pedsim.step(peds, *a, **k)
        _STATE["peds"], _STATE["t"] = new, _STATE["t"] + 1
        return new, info

    pm.observe, pm.step_unicycle = observe, step_unicycle
    pm.pedsim = types.SimpleNamespace(step=step, step_key=pedsim.step_key, SocialForceConfig=pedsim.SocialForceConfig)
    _INSTALLED = True
    return _STATE


def reset(scn) -> dict:
    """Start a new episode of scene ``scn``: t 0, its people, a zero command and its start pose."""
    state = install()
    state.clear()
    state.update(t=0, peds=scn.peds, cmd=np.zeros(2, np.float32), pose=np.asarray(scn.start))
    return state
