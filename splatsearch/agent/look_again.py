"""Where to look at an ambiguous object again (issue 23, the "look again" step).

The NVSM renders an object's local map from hemisphere cameras; what the robot never saw from
there (mostly the object's far side and its surroundings up to the views' edges) is a hole that
the completion has to invent. When a candidate's verification is ambiguous the agent can walk to
a viewpoint that sees what its local map lacks and take a real frame there instead.

:func:`choose_viewpoint` picks that viewpoint on the occupancy grid: around the object at about
``distance`` metres, at an azimuth far from those of the object's stored observations (and, when
the last NVSM run is known, near the cameras whose renders had the most holes), on a cell that
the FMM planner reaches from the robot within ``max_path`` metres and that sees the object
across the grid. Pure numpy on the grid; the policy (:mod:`splatsearch.agent.decision`) walks
there and turns to face the object.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from splatsearch.nav.grid import GridSpec, wrap_angle
from splatsearch.search.novel_views import camera_pose

#: metres charged per metre of path when viewpoints are compared (a tie-break toward nearer ones)
PATH_COST = 0.05
#: relative candidate distances tried around ``distance`` (metres added)
DISTANCE_STEPS = (0.0, -0.3, 0.3, 0.6)


@dataclass
class LookAgainView:
    """A chosen viewpoint: ``xy`` (2,) world metres where the robot should stand, ``yaw`` (rad) that
    faces the object from there, ``azimuth`` (rad) of the viewpoint around the object (from +x,
    counter-clockwise), ``score`` (novelty + hole fraction - path cost) and ``path`` (geodesic
    metres from the robot)."""

    xy: np.ndarray
    yaw: float
    azimuth: float
    score: float
    path: float


def azimuths_of(viewmats: Sequence[np.ndarray], centroid: Sequence[float]) -> np.ndarray:
    """(N,) azimuths (rad) around ``centroid`` (3,) of the camera centres of ``viewmats``
    (world-to-camera 4x4 each)."""
    c = np.asarray(centroid, np.float64)
    out = []
    for vm in viewmats:
        eye, _ = camera_pose(np.asarray(vm, np.float64))
        out.append(np.arctan2(eye[1] - c[1], eye[0] - c[0]))
    return np.asarray(out, np.float64)


def _angle_gap(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a - b| wrapped to [0, pi], broadcast."""
    return np.abs(wrap_angle(np.asarray(a)[..., None] - np.asarray(b)[None, ...]))


def line_of_sight(blocked: np.ndarray, spec: GridSpec, a_xy, b_xy, skip_end: float = 0.0) -> bool:
    """No blocked cell on the segment from ``a_xy`` to ``b_xy`` (world metres), leaving out the last
    ``skip_end`` metres before ``b_xy`` (the object's own footprint)."""
    a, b = np.asarray(a_xy, np.float64), np.asarray(b_xy, np.float64)
    seg = b - a
    length = float(np.linalg.norm(seg))
    reach = max(length - skip_end, 0.0)
    n = max(2, int(np.ceil(reach / (0.5 * spec.cell_size))) + 1)
    s = np.linspace(0.0, reach / max(length, 1e-9), n)
    rc = spec.world_to_cell(a + s[:, None] * seg)
    if not spec.in_bounds(rc).all():
        return False
    return not blocked[rc[:, 0], rc[:, 1]].any()


def choose_viewpoint(centroid: Sequence[float], extent_radius: float, spec: GridSpec, blocked: np.ndarray,
                     path_from_robot: np.ndarray, seen_azimuths: Sequence[float], *,
                     view_azimuths: Sequence[float] | None = None, view_holes: Sequence[float] | None = None,
                     distance: float = 1.6, max_path: float = 8.0, n_azimuths: int = 24,
                     min_gap_deg: float = 40.0) -> LookAgainView | None:
    """The viewpoint from which to look at an object again, or None when no cell qualifies.

    Args:
        centroid: (3,) object centre, world metres; extent_radius: metres (half its box diagonal).
        spec: the grid; blocked: (H, W) bool obstacle cells (occupied) for the line of sight.
        path_from_robot: (H, W) geodesic metres from the robot to every cell over the planner's
            traversable mask (obstacles inflated by the robot radius; inf where unreachable), e.g.
            ``FMMPlanner.distance_from(pose[:2])``: a finite value is a free cell the robot can
            stand on and reach.
        seen_azimuths: (N,) azimuths (rad) around the object of the cameras it was already
            observed from (its local map's frames).
        view_azimuths, view_holes: (V,) azimuths of the last NVSM run's cameras and the fraction of
            each render the local map left empty (opacity below the hole threshold); optional.
        distance: metres from the object's centre (horizontally) to stand at; tried also at
            :data:`DISTANCE_STEPS` around it, never closer than ``extent_radius + 0.4``.
        max_path: metres of path at most. n_azimuths: candidate azimuths around the object.
        min_gap_deg: a candidate must be at least this far in azimuth from every seen camera.

    Score of a candidate: its azimuth's gap to the nearest seen camera (as a fraction of 180
    degrees) + the hole fraction of the NVSM camera nearest to it in azimuth (0 without a run)
    - :data:`PATH_COST` x its path length.
    """
    c = np.asarray(centroid, np.float64).reshape(-1)[:2]
    blocked = np.asarray(blocked, bool)
    D = np.asarray(path_from_robot, np.float64)
    if blocked.shape != spec.shape or D.shape != spec.shape:
        raise ValueError(f"blocked and path_from_robot must have the grid's shape {spec.shape}")
    if n_azimuths < 1 or distance <= 0 or max_path <= 0:
        raise ValueError("need n_azimuths >= 1, distance > 0 and max_path > 0")
    seen = np.asarray(seen_azimuths, np.float64).reshape(-1)
    az = 2 * np.pi * np.arange(n_azimuths) / n_azimuths
    novelty = _angle_gap(az, seen).min(1) / np.pi if len(seen) else np.ones(n_azimuths)
    holes = np.zeros(n_azimuths)
    if view_azimuths is not None and view_holes is not None and len(view_azimuths):
        va = np.asarray(view_azimuths, np.float64).reshape(-1)
        vh = np.asarray(view_holes, np.float64).reshape(-1)
        if va.shape != vh.shape:
            raise ValueError("view_azimuths and view_holes must have the same length")
        holes = vh[np.argmin(_angle_gap(az, va), axis=1)]
    near = float(extent_radius) + 0.4
    best: LookAgainView | None = None
    for k, a in enumerate(az):
        if novelty[k] * np.pi < np.radians(min_gap_deg):
            continue
        u = np.array([np.cos(a), np.sin(a)])
        for dd in DISTANCE_STEPS:
            r = max(distance + dd, near)
            xy = c + r * u
            rc = spec.world_to_cell(xy)
            if not spec.in_bounds(rc):
                continue
            p = float(D[rc[0], rc[1]])
            if not np.isfinite(p) or p > max_path:
                continue
            if not line_of_sight(blocked, spec, xy, c, skip_end=float(extent_radius)):
                continue
            score = float(novelty[k] + holes[k] - PATH_COST * p)
            if best is None or score > best.score + 1e-9:
                at = spec.cell_to_world(rc).astype(np.float64)  # the cell's centre
                yaw = float(np.arctan2(c[1] - at[1], c[0] - at[0]))
                best = LookAgainView(at, yaw, float(a), score, p)
            break  # the first distance that works at this azimuth (the preferred one first)
    return best
