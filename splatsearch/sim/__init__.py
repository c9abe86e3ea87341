"""Procedural indoor RGB-D simulator and instance-image-goal (IIN) episodes.

    house = make_house(seed)                      # multi-room house, deterministic per seed
    env = HouseEnv(house)                         # Warp ray-cast RGB-D + instance/class ids
    episodes = make_episodes(house, 10, "val-hard", seed=0, env=env)
    obs = env.reset(episodes[0].start); obs = env.step("move_forward")
"""

from .env import ACTIONS, HouseEnv, Observation, OdometryNoise, camera_viewmat, intrinsics, look_at_viewmat
from .episodes import (
    SPLITS,
    Episode,
    EpisodeJudge,
    goal_image,
    goal_viewpoints,
    house_for_episode,
    load_episodes,
    make_episodes,
    save_episodes,
    spl,
)
from .house import CLASS_IDS, CLASS_NAMES, GOAL_CLASSES, House, Room, SceneObject, make_house
from .meshio import load_house, save_house
from .navgrid import NavGrid, build_navgrid, geodesic_distance
from .raycast import Frame, HouseRenderer, SensorNoise
from . import preview  # noqa: E402,F401

__all__ = [
    "ACTIONS", "CLASS_IDS", "CLASS_NAMES", "GOAL_CLASSES", "SPLITS", "Episode", "EpisodeJudge", "Frame", "House",
    "HouseEnv", "HouseRenderer", "NavGrid", "Observation", "OdometryNoise", "Room", "SceneObject", "SensorNoise",
    "build_navgrid", "camera_viewmat", "geodesic_distance", "goal_image", "goal_viewpoints", "house_for_episode", "intrinsics",
    "load_episodes", "load_house", "look_at_viewmat", "make_episodes", "make_house", "save_episodes", "save_house",
    "spl",
]
