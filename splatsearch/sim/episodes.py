"""Instance-image-goal (IIN) episodes, success and SPL.

An episode is a start pose on navigable space and a goal object instance with its goal image.
The split decides how the goal camera is placed:

* ``val``: a navigable viewpoint at camera height (1.31 m), facing the object.
* ``val-hard`` (thesis Section 4.4.1): sampled on a sphere around the object centroid: radius
  U[0.5, 2.5] m, azimuth in (0, pi] (measured from the object's front), camera height
  U[1.0, 2.0] m, looking at the centroid with the direction perturbed by up to 10 degrees.

Success is ``stop`` within 1.0 m (geodesic) of the goal's navigable viewpoints, which are the
navigable cells within 1.0 m of the object's footprint. ``d*`` is the FMM geodesic distance
from the start to those viewpoints, and ``SPL = S * d* / max(d*, p)``.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import asdict, dataclass

import numpy as np
import warp as wp

from .env import CAMERA_HEIGHT, HouseEnv, intrinsics, look_at_viewmat
from .house import GENERATOR_VERSION, GOAL_CLASSES, House, SceneObject
from .navgrid import NavGrid

SPLITS = ("val", "val-hard")
SUCCESS_DISTANCE = 1.0
VIEWPOINT_RADIUS = 1.0
MIN_GOAL_PIXELS = 0.02  # the goal instance must cover this fraction of the goal image


@dataclass
class Episode:
    """Everything needed to replay an episode (the house is rebuilt from its seed)."""

    episode_id: int
    split: str
    house_seed: int
    house_n_rooms: int
    generator_version: int
    start: list  # (x, y, yaw)
    goal_instance_id: int
    goal_class: str
    goal_viewmat: list  # 4x4 world-to-camera of the goal image
    goal_K: list  # 3x3
    goal_width: int
    goal_height: int
    d_star: float
    success_distance: float = SUCCESS_DISTANCE
    max_steps: int = 1000
    identical_furniture: bool = False  # the house was built with make_house(..., identical_furniture=True)

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> Episode:
        missing = [f.name for f in dataclasses.fields(cls) if f.name not in d and f.default is dataclasses.MISSING]
        if missing:
            raise ValueError(f"episode JSON is missing fields: {missing}")
        return cls(**{k: d[k] for k in cls.__dataclass_fields__ if k in d})


def save_episodes(episodes: list[Episode], path: str) -> None:
    """Write episodes as JSON, atomically (temporary file, then rename)."""
    from splatsearch.io import atomic_write_bytes

    data = json.dumps({"format": "splatsearch-iin-episodes", "version": 1,
                       "episodes": [e.to_json() for e in episodes]}, indent=1)
    atomic_write_bytes(path, data.encode())


def load_episodes(path: str) -> list[Episode]:
    """Read episodes written by :func:`save_episodes`; rejects other or corrupt files clearly."""
    try:
        with open(path) as f:
            d = json.load(f)
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not valid JSON ({e})") from e
    if not isinstance(d, dict) or d.get("format") != "splatsearch-iin-episodes":
        raise ValueError(f"{path}: not a splatsearch episodes file")
    return [Episode.from_json(e) for e in d["episodes"]]


def goal_viewpoints(nav: NavGrid, obj: SceneObject, radius: float = VIEWPOINT_RADIUS) -> np.ndarray:
    """(H, W) bool: navigable cells within ``radius`` of the object's footprint rectangle."""
    H, W = nav.shape
    rows, cols = np.mgrid[0:H, 0:W]
    xy = nav.cell_to_world(np.stack([rows, cols], -1))
    half = obj.size[:2] / 2
    dx = np.maximum(np.abs(xy[..., 0] - obj.center[0]) - half[0], 0)
    dy = np.maximum(np.abs(xy[..., 1] - obj.center[1]) - half[1], 0)
    return nav.navigable & (np.hypot(dx, dy) <= radius)


def spl(success: bool, d_star: float, path_length: float) -> float:
    """Success weighted by path length: S * d* / max(d*, p)."""
    if not np.isfinite(d_star) or d_star < 0 or path_length < 0:
        raise ValueError(f"need finite d* >= 0 and path length >= 0, got {d_star}, {path_length}")
    if not success:
        return 0.0
    if d_star == 0 and path_length == 0:
        return 1.0
    return float(d_star / max(d_star, path_length))


class EpisodeJudge:
    """Distance-to-goal field of one episode: success test and d* from any pose."""

    def __init__(self, nav: NavGrid, obj: SceneObject, success_distance: float = SUCCESS_DISTANCE):
        self.nav = nav
        self.viewpoints = goal_viewpoints(nav, obj)
        if not self.viewpoints.any():
            raise ValueError(f"object {obj.instance_id} ({obj.class_name}) has no navigable viewpoint")
        self.dist = nav.geodesic_from(self.viewpoints)
        self.success_distance = success_distance

    def distance(self, xy) -> float:
        rc = self.nav.world_to_cell(xy)
        if not self.nav.in_bounds(rc):
            return float("inf")
        return float(self.dist[rc[0], rc[1]])

    def success(self, xy) -> bool:
        return self.distance(xy) <= self.success_distance


def _visible_fraction(env: HouseEnv, viewmat, obj: SceneObject, K, w, h) -> float:
    f = env.renderer.render(viewmat, K, w, h, max_depth=env.max_depth)
    return float((f.instance == obj.instance_id).mean())


@wp.kernel(enable_backward=False)
def _probe_kernel(mesh: wp.uint64, o: wp.vec3, dirs: wp.array(dtype=wp.vec3), dist: wp.array(dtype=float)):
    i = wp.tid()
    q = wp.mesh_query_ray(mesh, o, dirs[i], 1.0e4)
    dist[i] = wp.inf
    if q.result:
        if wp.dot(q.normal, dirs[i]) > 0.0:
            dist[i] = -1.0  # a back face: the point is inside a closed object
        else:
            dist[i] = q.t


_PROBE_DIRS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float32)


def _free_point(env: HouseEnv, p: np.ndarray, clearance: float = 0.15) -> bool:
    """True if a camera at p is inside the house, not inside geometry, and ``clearance`` m from
    it along the six axis directions."""
    dist = wp.zeros(len(_PROBE_DIRS), dtype=float)
    wp.launch(_probe_kernel, dim=len(_PROBE_DIRS),
              inputs=[env.renderer.mesh.id, wp.vec3(*p.astype(np.float32)), wp.array(_PROBE_DIRS, dtype=wp.vec3)],
              outputs=[dist])
    hits = dist.numpy()
    return bool(np.all(np.isfinite(hits)) and np.all(hits >= clearance))


def sample_goal_camera(env: HouseEnv, obj: SceneObject, split: str, rng: np.random.Generator,
                       width: int, height: int, tries: int = 200) -> np.ndarray:
    """World-to-camera 4x4 of a goal image of ``obj`` for ``split`` (see module docstring)."""
    K = intrinsics(width, height)
    nav = env.nav
    c = obj.center.copy()
    if split == "val":
        rows, cols = np.nonzero(nav.navigable)
        xy = nav.cell_to_world(np.stack([rows, cols], -1))
        dist = np.hypot(xy[:, 0] - c[0], xy[:, 1] - c[1])
        cand = np.flatnonzero((dist >= 0.8) & (dist <= 3.0))
        for _ in range(tries if len(cand) else 0):
            p = xy[rng.choice(cand)]
            vm = look_at_viewmat([p[0], p[1], CAMERA_HEIGHT], c)
            if _visible_fraction(env, vm, obj, K, width, height) >= MIN_GOAL_PIXELS:
                return vm
    elif split == "val-hard":
        for _ in range(tries):
            r = rng.uniform(0.5, 2.5)
            az = obj.yaw - np.pi / 2 + rng.uniform(1e-6, np.pi)  # the half circle in front of the object
            z = rng.uniform(1.0, 2.0)
            horiz2 = r * r - (z - c[2]) ** 2
            if horiz2 <= 0.05:
                continue
            horiz = np.sqrt(horiz2)
            eye = np.array([c[0] + horiz * np.cos(az), c[1] + horiz * np.sin(az), z])
            if not _free_point(env, eye):
                continue
            target = c + rng.uniform(-1, 1, 3) * np.tan(np.radians(10.0)) * np.linalg.norm(c - eye) / np.sqrt(3)
            vm = look_at_viewmat(eye, target)
            if _visible_fraction(env, vm, obj, K, width, height) >= MIN_GOAL_PIXELS:
                return vm
    else:
        raise ValueError(f"unknown split {split!r}; expected one of {SPLITS}")
    raise RuntimeError(f"no goal view found for object {obj.instance_id} ({obj.class_name})")


def make_episodes(house: House, n: int, split: str = "val", seed: int = 0, *, env: HouseEnv | None = None,
                  goal_classes: tuple[str, ...] = GOAL_CLASSES, width: int = 320, height: int = 240,
                  min_d_star: float = 1.5) -> list[Episode]:
    """Sample ``n`` reproducible episodes in ``house``.

    Raises:
        ValueError: for an unknown split or class, n < 0, or a house with no goal objects.
    """
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; expected one of {SPLITS}")
    bad = [c for c in goal_classes if c not in GOAL_CLASSES]
    if bad:
        raise ValueError(f"unknown goal class(es) {bad}; known: {GOAL_CLASSES}")
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    env = env or HouseEnv(house)
    nav = env.nav
    rng = np.random.default_rng([int(seed), SPLITS.index(split), int(house.seed or 0)])
    objs = [o for o in house.objects if o.class_name in goal_classes]
    if not objs and n > 0:
        raise ValueError(f"house has no objects of the classes {goal_classes}")
    episodes: list[Episode] = []
    judges: dict[int, EpisodeJudge | None] = {}
    nav_cells = np.argwhere(nav.navigable)
    attempts = 0
    while len(episodes) < n:
        attempts += 1
        if attempts > 50 * max(n, 1):
            raise RuntimeError(f"could only sample {len(episodes)} of {n} episodes")
        obj = objs[int(rng.integers(0, len(objs)))]
        if obj.instance_id not in judges:
            try:
                judges[obj.instance_id] = EpisodeJudge(nav, obj)
            except ValueError:
                judges[obj.instance_id] = None
        judge = judges[obj.instance_id]
        if judge is None:
            continue
        rc = nav_cells[int(rng.integers(0, len(nav_cells)))]
        d_star = float(judge.dist[rc[0], rc[1]])
        if not np.isfinite(d_star) or d_star < min_d_star:
            continue
        try:
            vm = sample_goal_camera(env, obj, split, rng, width, height)
        except RuntimeError:
            judges[obj.instance_id] = None
            continue
        xy = nav.cell_to_world(rc)
        episodes.append(Episode(
            episode_id=len(episodes), split=split, house_seed=int(house.seed or 0), house_n_rooms=len(house.rooms), generator_version=GENERATOR_VERSION,
            start=[float(xy[0]), float(xy[1]), float(rng.uniform(-np.pi, np.pi))],
            goal_instance_id=obj.instance_id, goal_class=obj.class_name,
            goal_viewmat=np.asarray(vm, float).tolist(), goal_K=intrinsics(width, height).tolist(),
            goal_width=width, goal_height=height, d_star=d_star,
            identical_furniture=house.identical_furniture))
    return episodes


def house_for_episode(ep: Episode) -> House:
    """Rebuild the house an episode was sampled in (from its seed, room count and furniture mode)."""
    from .house import make_house

    if ep.generator_version != GENERATOR_VERSION:
        raise ValueError(f"episode was made by house generator v{ep.generator_version}; this is v{GENERATOR_VERSION}")
    # the stored count is len(house.rooms) of the sampled house; when the seed drew a different
    # count (the layout can merge rooms: houses 62, 82 and 1005 of the first 112), passing it
    # builds another house, so the seed alone is tried first
    same = bool(ep.identical_furniture)
    house = make_house(ep.house_seed, identical_furniture=same)
    if len(house.rooms) == ep.house_n_rooms:
        return house
    return make_house(ep.house_seed, ep.house_n_rooms, identical_furniture=same)


def goal_image(env: HouseEnv, ep: Episode):
    """Re-render an episode's goal image (a :class:`Frame`)."""
    return env.renderer.render(np.asarray(ep.goal_viewmat), np.asarray(ep.goal_K), ep.goal_width, ep.goal_height,
                               max_depth=env.max_depth)
