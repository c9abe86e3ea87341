"""The SplatSearch agent, in three rooms: perception, verification, decision.

    agent = SplatSearchAgent(K, W, H, goal_rgb, "chair", start_pose, config=AgentConfig())
    info = agent.act(rgb, depth, viewmat, pose, frame)      # -> StepInfo(action, status, ...)

Modules: ``config`` (AgentConfig, VARIANTS, Strategy, resolve_variant), ``perception``
(Perception: online map, detection, lifting, object DB, colour cue), ``verification``
(Verifier: crop matching, NVSM, the goal decision), ``decision`` (SearchPolicy: target choice,
fallback, the action), ``core`` (SplatSearchAgent, StepInfo).
"""

from .config import VARIANTS, AgentConfig, Strategy, resolve_variant
from .core import MIN_GOAL_SIDE, SplatSearchAgent, StepInfo
from .decision import FALLBACK_COLOUR_MARGIN, FALLBACK_MATCH_MARGIN, SearchPolicy
from .perception import LIFT_TOLERANCE, NewView, Perception, crop_around
from .verification import MATCH_CROP_MARGIN, NovelViews, Verifier

__all__ = [
    "FALLBACK_COLOUR_MARGIN",
    "FALLBACK_MATCH_MARGIN",
    "LIFT_TOLERANCE",
    "MATCH_CROP_MARGIN",
    "MIN_GOAL_SIDE",
    "VARIANTS",
    "AgentConfig",
    "NewView",
    "NovelViews",
    "Perception",
    "SearchPolicy",
    "SplatSearchAgent",
    "StepInfo",
    "Strategy",
    "Verifier",
    "crop_around",
    "resolve_variant",
]
