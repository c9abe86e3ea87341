"""CoNVOI on a JAX DWA, with the pedestrian world it is run and scored in.

Modules: ``geometry`` (frames, capsule walls, distance fields), ``costs`` and ``dwa`` (the
Dynamic Window Approach over a registry of Nav2-style critics), ``controller`` (PID trajectory
follower), ``pedsim`` (seeded social-force pedestrians with groups and hard collisions),
``scenarios`` (hallway, blind corner, static and dynamic groups, doorway, crossing),
``perception`` (what the robot sees of people and walls), ``context`` (context classifier and
behaviour prompt), ``mmvm`` (multi-modal visual marking), ``vlm`` (the VLM protocol: rules,
replay, an OpenAI-compatible HTTP client), ``pipeline`` (CoNVOI: marking -> VLM -> reference
path, extrapolation and re-query), ``runner`` (episodes of the expert, DWA and CoNVOI),
``metrics`` (trajectory metrics in JAX), ``report`` (Tables I-II) and ``viewer`` (viser).
The public names are re-exported by :mod:`splatsearch.social`.
"""
