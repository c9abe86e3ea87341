"""Social-navigation layer of splatsearch: a JAX DWA with Nav2-style critics, CoNVOI (context
prompts, multi-modal visual marking, VLM reference paths, extrapolation and re-query), a JAX
social-force pedestrian simulator with groups and hard collisions, the OLiVia-Nav scenarios and
PID navigation controller, and trajectory metrics in JAX.

    from splatsearch.social import make_scenario, run_episode, CoNVOI, RuleBasedVLM
    scn = make_scenario("hallway", seed=0)
    expert = run_episode(scn, "expert")                      # privileged "teleoperation" reference
    dwa = run_episode(scn, "dwa")
    cv = CoNVOI(RuleBasedVLM()); cv.set_ground_truth(expert.robot)
    convoi = run_episode(scn, "convoi", convoi=cv)
    frechet(convoi.robot, expert.robot)

Frames: world x, y in metres, z up, yaw counter-clockwise; the robot frame is x forward, y left
(CoNVOI III-A); cameras use the OpenCV frame. Grids follow :mod:`splatsearch.nav.grid`.
"""

from .context import (
    CONTEXTS,
    PROMPT_TEMPLATE,
    CLIPContextClassifier,
    ContextClassifier,
    ContextResult,
    RuleContextClassifier,
    SceneObservation,
    behaviour_prompt,
)
from .controller import FollowerConfig, PIDGains, follow_step, pid_update, track
from .convoi import CoNVOI, CoNVOIConfig
from .costs import CRITICS, CostInputs, CriticSpec, register_critic
from .dwa import (
    CONVOI_PAPER_CRITICS,
    DEFAULT_CRITICS,
    DWAConfig,
    DWAInputs,
    DWAResult,
    constant_velocity_forecast,
    dynamic_window,
    make_inputs,
    plan,
    reference_critic,
    rollout,
)
from .geometry import (
    DistanceField,
    distance_field_from_capsules,
    distance_field_from_occupancy,
    field_lookup,
)
from .metrics import (
    collision_count,
    cosine_similarity,
    fraction_unacceptable,
    frechet,
    hausdorff,
    mean_velocity,
    min_distance_to_people,
    mse,
    normalized_length,
    path_length,
    path_unacceptable,
    psv_duration,
    reference_path_error,
    success,
)
from .mmvm import (
    CameraModel,
    MarkerGrid,
    Markers,
    candidate_grid,
    grid_to_image_homography,
    mark,
    render_view,
)
from .pedsim import PedState, SocialForceConfig, make_state
from .runner import PLANNERS, EpisodeResult, run_episode
from .scenarios import SCENARIOS, THESIS_SCENARIOS, Scenario, make_scenario
from .vlm import (
    VLM,
    MarkerScene,
    OpenAICompatibleVLM,
    ReplayVLM,
    RuleBasedVLM,
    VLMResult,
    parse_labels,
)

__all__ = [
    "CONTEXTS",
    "CONVOI_PAPER_CRITICS",
    "CRITICS",
    "DEFAULT_CRITICS",
    "PLANNERS",
    "PROMPT_TEMPLATE",
    "SCENARIOS",
    "THESIS_SCENARIOS",
    "VLM",
    "CLIPContextClassifier",
    "CameraModel",
    "CoNVOI",
    "CoNVOIConfig",
    "ContextClassifier",
    "ContextResult",
    "CostInputs",
    "CriticSpec",
    "DWAConfig",
    "DWAInputs",
    "DWAResult",
    "DistanceField",
    "EpisodeResult",
    "FollowerConfig",
    "MarkerGrid",
    "MarkerScene",
    "Markers",
    "OpenAICompatibleVLM",
    "PIDGains",
    "PedState",
    "ReplayVLM",
    "RuleBasedVLM",
    "RuleContextClassifier",
    "Scenario",
    "SceneObservation",
    "SocialForceConfig",
    "VLMResult",
    "behaviour_prompt",
    "candidate_grid",
    "collision_count",
    "constant_velocity_forecast",
    "cosine_similarity",
    "distance_field_from_capsules",
    "distance_field_from_occupancy",
    "dynamic_window",
    "field_lookup",
    "follow_step",
    "fraction_unacceptable",
    "frechet",
    "grid_to_image_homography",
    "hausdorff",
    "make_inputs",
    "make_scenario",
    "make_state",
    "mark",
    "mean_velocity",
    "min_distance_to_people",
    "mse",
    "normalized_length",
    "parse_labels",
    "path_length",
    "path_unacceptable",
    "pid_update",
    "plan",
    "psv_duration",
    "reference_critic",
    "reference_path_error",
    "register_critic",
    "render_view",
    "rollout",
    "run_episode",
    "success",
    "track",
]
