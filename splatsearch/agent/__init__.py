"""The SplatSearch agent, in three rooms: perception, verification, decision.

    agent = SplatSearchAgent(K, W, H, goal_rgb, "chair", start_pose, config=AgentConfig())
    info = agent.act(rgb, depth, viewmat, pose, frame)      # -> StepInfo(action, status, ...)

Modules: ``config`` (AgentConfig, VARIANTS, Strategy, resolve_variant), ``perception``
(Perception: online map, detection, lifting, object DB, colour cue), ``verification``
(Verifier: crop matching, NVSM, the goal decision), ``decision`` (SearchPolicy: target choice,
fallback, the action), ``core`` (SplatSearchAgent, StepInfo). ``VARIANTS`` is defined without
heavy imports (``variants``); the other names load on first use.
"""

from __future__ import annotations

from splatsearch._lazy import lazy_exports

from .variants import VARIANTS  # noqa: F401 - light, read by the CLI parser

#: public name -> the submodule that defines it
_EXPORTS = {
    "AgentConfig": "config", "Strategy": "config", "resolve_variant": "config",
    "MIN_GOAL_SIDE": "core", "SplatSearchAgent": "core", "StepInfo": "core",
    "FALLBACK_COLOUR_MARGIN": "decision", "FALLBACK_MATCH_MARGIN": "decision", "SearchPolicy": "decision",
    "LIFT_TOLERANCE": "perception", "NewView": "perception", "Perception": "perception", "crop_around": "perception",
    "MATCH_CROP_MARGIN": "verification", "NovelViews": "verification", "Verifier": "verification",
}
__all__ = sorted([*_EXPORTS, "VARIANTS"])


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())
