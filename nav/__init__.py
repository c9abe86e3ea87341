"""Navigation layer of splatsearch: occupancy grid, frontiers, value and confidence maps
(thesis eq 11-12), FMM planner (scikit-fmm) and the exploration utility (eq 19-20).

    spec = GridSpec.centered(start_xy)                    # 1000 x 1000 cells of 5 cm
    planner = ExplorationPlanner(spec, ExplorationConfig(alpha=1.0))
    planner.observe(depth, viewmat, K, pose, rgb)         # occupancy + value map
    action = planner.act(pose).action                     # "move_forward" / "turn_left" / ...

Grid convention (same as ``splatsearch.sim.navgrid``): ``grid[row, col]`` covers
``x in [ox + col*c, ox + (col+1)*c)``, ``y in [oy + row*c, oy + (row+1)*c)``.
"""

from .encoders import (
    ColorTextureEncoder,
    ImageEncoder,
    ModelUnavailable,
    OpenCLIPEncoder,
    TransformersImageEncoder,
    cosine,
)
from .exploration import (
    Decision,
    ExplorationConfig,
    ExplorationPlanner,
    ObjectScore,
    coverage,
    inverse_distance_score,
    normalise,
    object_score,
    utility,
)
from .fmm import ACTIONS, FMMPlanner, Plan, Unreachable, geodesic_distance
from .frontiers import Frontier, attach_distances, extract_frontiers, frontier_cells, significant_unknown
from .grid import GridSpec, disk
from .occupancy import FREE, OCCUPIED, UNKNOWN, FovFootprint, OccupancyGrid, level_viewmat
from .value_map import ValueMap, confidence, fuse

__all__ = [
    "ACTIONS", "FREE", "OCCUPIED", "UNKNOWN", "ColorTextureEncoder", "Decision", "ExplorationConfig",
    "ExplorationPlanner", "FMMPlanner", "FovFootprint", "Frontier", "GridSpec", "ImageEncoder", "ModelUnavailable",
    "ObjectScore", "OccupancyGrid", "OpenCLIPEncoder", "Plan", "TransformersImageEncoder", "Unreachable", "ValueMap",
    "attach_distances", "confidence", "cosine", "coverage", "disk", "extract_frontiers", "frontier_cells", "fuse",
    "geodesic_distance", "inverse_distance_score", "level_viewmat", "normalise", "object_score",
    "significant_unknown", "utility",
]
