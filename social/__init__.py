"""Social navigation, as two systems over one pedestrian world.

``splatsearch.social.convoi``: CoNVOI on a JAX DWA (context prompts, multi-modal visual marking,
VLM reference paths, extrapolation and re-query; Nav2-style critics), the seeded social-force
pedestrian simulator and its scenarios, the PID follower, the episode runner and the trajectory
metrics. ``splatsearch.social.olivia``: OLiVia-Nav (SC-CLIP, TPN, TSM, LLU, the tokenizer, its
data from the simulator and its training), which runs in the same scenarios and is scored with
the same metrics.

    from splatsearch.social import make_scenario, run_episode, CoNVOI, RuleBasedVLM, frechet
    scn = make_scenario("hallway", seed=0)
    expert = run_episode(scn, "expert")                      # privileged "teleoperation" reference
    dwa = run_episode(scn, "dwa")
    cv = CoNVOI(RuleBasedVLM()); cv.set_ground_truth(expert.robot)
    convoi = run_episode(scn, "convoi", convoi=cv)
    frechet(convoi.robot, expert.robot)

The names below are loaded on first use, so ``import splatsearch.social`` (and the CLI that
registers the social commands) does not import JAX.

Frames: world x, y in metres, z up, yaw counter-clockwise; the robot frame is x forward, y left
(CoNVOI III-A); cameras use the OpenCV frame. Grids follow :mod:`splatsearch.nav.grid`.
"""

from __future__ import annotations

from splatsearch._lazy import lazy_exports

#: public name -> the submodule that defines it
_EXPORTS = {
    # convoi.context
    "CLIPContextClassifier": "convoi.context",
    "CONTEXTS": "convoi.context",
    "ContextClassifier": "convoi.context",
    "ContextResult": "convoi.context",
    "PROMPT_TEMPLATE": "convoi.context",
    "RuleContextClassifier": "convoi.context",
    "SceneObservation": "convoi.context",
    "behaviour_prompt": "convoi.context",
    # convoi.controller
    "FollowerConfig": "convoi.controller",
    "PIDGains": "convoi.controller",
    "follow_step": "convoi.controller",
    "pid_update": "convoi.controller",
    "track": "convoi.controller",
    # convoi.costs
    "CRITICS": "convoi.costs",
    "CostInputs": "convoi.costs",
    "CriticSpec": "convoi.costs",
    "register_critic": "convoi.costs",
    # convoi.dwa
    "DEFAULT_CRITICS": "convoi.dwa",
    "DWAConfig": "convoi.dwa",
    "DWAInputs": "convoi.dwa",
    "DWAResult": "convoi.dwa",
    "constant_velocity_forecast": "convoi.dwa",
    "dynamic_window": "convoi.dwa",
    "make_inputs": "convoi.dwa",
    "plan": "convoi.dwa",
    "reference_critic": "convoi.dwa",
    "rollout": "convoi.dwa",
    # convoi.geometry
    "DistanceField": "convoi.geometry",
    "distance_field_from_capsules": "convoi.geometry",
    "distance_field_from_occupancy": "convoi.geometry",
    "field_lookup": "convoi.geometry",
    # convoi.metrics
    "collision_count": "convoi.metrics",
    "cosine_similarity": "convoi.metrics",
    "fraction_unacceptable": "convoi.metrics",
    "frechet": "convoi.metrics",
    "hausdorff": "convoi.metrics",
    "mean_velocity": "convoi.metrics",
    "min_distance_to_people": "convoi.metrics",
    "mse": "convoi.metrics",
    "normalized_length": "convoi.metrics",
    "path_length": "convoi.metrics",
    "path_unacceptable": "convoi.metrics",
    "psv_duration": "convoi.metrics",
    "reference_path_error": "convoi.metrics",
    "success": "convoi.metrics",
    # convoi.mmvm
    "CameraModel": "convoi.mmvm",
    "MarkerGrid": "convoi.mmvm",
    "Markers": "convoi.mmvm",
    "candidate_grid": "convoi.mmvm",
    "grid_to_image_homography": "convoi.mmvm",
    "mark": "convoi.mmvm",
    "render_view": "convoi.mmvm",
    # convoi.pedsim
    "PedState": "convoi.pedsim",
    "SocialForceConfig": "convoi.pedsim",
    "make_state": "convoi.pedsim",
    # convoi.pipeline
    "CoNVOI": "convoi.pipeline",
    "CoNVOIConfig": "convoi.pipeline",
    # convoi.runner
    "EpisodeResult": "convoi.runner",
    "PLANNERS": "convoi.runner",
    "run_episode": "convoi.runner",
    # convoi.scenarios
    "SCENARIOS": "convoi.scenario_names",
    "Scenario": "convoi.scenarios",
    "THESIS_SCENARIOS": "convoi.scenario_names",
    "make_scenario": "convoi.scenarios",
    # convoi.vlm
    "MarkerScene": "convoi.vlm",
    "OpenAICompatibleVLM": "convoi.vlm",
    "ReplayVLM": "convoi.vlm",
    "RuleBasedVLM": "convoi.vlm",
    "VLM": "convoi.vlm",
    "VLMResult": "convoi.vlm",
    "parse_labels": "convoi.vlm",
}

__all__ = sorted(_EXPORTS)


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())
