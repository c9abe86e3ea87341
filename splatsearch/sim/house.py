"""Procedural multi-room houses built from trimesh primitives, deterministic per seed.

A house is a single triangle mesh with per-face material, instance id and class id, plus the
room rectangles and the object list. The layout is a binary space partition of a rectangle, with
an optional corridor strip; every split gets a doorway, so all rooms are connected. Walls are
boxes along the merged room edges with door gaps and lintels. Furniture of the six goal classes
(several instances each, every instance with its own materials) and distractors are placed on
a free-space grid so that the house stays connected.

World frame: metres, z up, floor at z = 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

from .materials import MaterialTable, random_material

GOAL_CLASSES = ("chair", "sofa", "table", "tv_monitor", "plant", "bed")
DISTRACTOR_CLASSES = ("cabinet", "lamp", "shelf")
STRUCTURE_CLASSES = ("wall", "floor", "ceiling")
#: class id 0 means "no hit"; goal classes are 1..6
CLASS_NAMES = ("void",) + GOAL_CLASSES + DISTRACTOR_CLASSES + STRUCTURE_CLASSES
CLASS_IDS = {name: i for i, name in enumerate(CLASS_NAMES)}

WALL_HEIGHT = 2.6
WALL_THICKNESS = 0.1
DOOR_WIDTH = 0.95
DOOR_HEIGHT = 2.1
CORRIDOR_WIDTH = 1.4
MIN_ROOM = 2.6
GENERATOR_VERSION = 1


@dataclass
class Room:
    index: int
    x0: float
    y0: float
    x1: float
    y1: float
    kind: str  # "living", "bedroom", "kitchen", "office", "corridor"

    @property
    def area(self) -> float:
        return (self.x1 - self.x0) * (self.y1 - self.y0)

    @property
    def center(self) -> np.ndarray:
        return np.array([(self.x0 + self.x1) / 2, (self.y0 + self.y1) / 2])


@dataclass
class SceneObject:
    instance_id: int
    class_name: str
    center: np.ndarray  # (3,) AABB centre, metres
    size: np.ndarray  # (3,) AABB extents, metres
    yaw: float  # radians, multiples of pi/2
    room: int

    @property
    def class_id(self) -> int:
        return CLASS_IDS[self.class_name]

    def to_json(self) -> dict:
        return {"instance_id": self.instance_id, "class_name": self.class_name, "center": self.center.tolist(),
                "size": self.size.tolist(), "yaw": self.yaw, "room": self.room}

    @classmethod
    def from_json(cls, d: dict) -> SceneObject:
        return cls(int(d["instance_id"]), d["class_name"], np.asarray(d["center"], float),
                   np.asarray(d["size"], float), float(d["yaw"]), int(d["room"]))


@dataclass
class House:
    """Triangle mesh of a house with per-face labels, rooms and objects.

    vertices (V, 3) float32 m; faces (F, 3) int32; face_material (F,) int32 (-1: vertex colour);
    face_instance (F,) int32 (0: none); face_class (F,) int32 (see ``CLASS_NAMES``);
    vertex_colors (V, 3) float32 in [0, 1].
    """

    seed: int | None
    vertices: np.ndarray
    faces: np.ndarray
    face_material: np.ndarray
    face_instance: np.ndarray
    face_class: np.ndarray
    vertex_colors: np.ndarray
    materials: MaterialTable
    rooms: list[Room] = field(default_factory=list)
    objects: list[SceneObject] = field(default_factory=list)
    wall_height: float = WALL_HEIGHT
    doors: list[tuple[str, float, float, float]] = field(default_factory=list)  # (axis, coord, lo, hi)
    identical_furniture: bool = False  # one model (shape and materials) per furniture class

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) min and max corner of the mesh."""
        return np.stack([self.vertices.min(0), self.vertices.max(0)])

    def object(self, instance_id: int) -> SceneObject:
        for o in self.objects:
            if o.instance_id == instance_id:
                return o
        raise KeyError(f"no object with instance id {instance_id}")

    def goal_objects(self) -> list[SceneObject]:
        return [o for o in self.objects if o.class_name in GOAL_CLASSES]

    def to_trimesh(self) -> trimesh.Trimesh:
        return trimesh.Trimesh(self.vertices, self.faces, process=False)


# ---------------------------------------------------------------------------------------------
# layout
# ---------------------------------------------------------------------------------------------

def _bsp(rng: np.random.Generator, rect, n: int, splits: list) -> list[tuple[float, float, float, float]]:
    """Split ``rect`` into n leaves; records every split as (axis, coord, rectA, rectB)."""
    leaves = [rect]
    while len(leaves) < n:
        order = sorted(range(len(leaves)), key=lambda i: -((leaves[i][2] - leaves[i][0]) * (leaves[i][3] - leaves[i][1])))
        for i in order:
            x0, y0, x1, y1 = leaves[i]
            w, h = x1 - x0, y1 - y0
            axis = "x" if w >= h else "y"
            length = w if axis == "x" else h
            if length < 2 * MIN_ROOM:
                continue
            lo = max(MIN_ROOM, 0.35 * length)
            cut = float(rng.uniform(lo, length - lo))
            if axis == "x":
                a, b = (x0, y0, x0 + cut, y1), (x0 + cut, y0, x1, y1)
                splits.append(("x", x0 + cut))
            else:
                a, b = (x0, y0, x1, y0 + cut), (x0, y0 + cut, x1, y1)
                splits.append(("y", y0 + cut))
            leaves[i:i + 1] = [a, b]
            break
        else:
            break
    return leaves


def _shared(a: Room, b: Room) -> tuple[str, float, float, float] | None:
    """The edge segment two rooms share, as (axis, coord, lo, hi): axis "x" = a vertical wall at x=coord."""
    eps = 1e-6
    for ra, rb in ((a, b), (b, a)):
        if abs(ra.x1 - rb.x0) < eps:
            lo, hi = max(ra.y0, rb.y0), min(ra.y1, rb.y1)
            if hi - lo > eps:
                return ("x", ra.x1, lo, hi)
        if abs(ra.y1 - rb.y0) < eps:
            lo, hi = max(ra.x0, rb.x0), min(ra.x1, rb.x1)
            if hi - lo > eps:
                return ("y", ra.y1, lo, hi)
    return None


def make_layout(rng: np.random.Generator, n_rooms: int) -> tuple[list[Room], list[tuple[str, float, float, float]]]:
    """Rooms (a corridor included for 5+ rooms) and doors, with every room reachable."""
    area = sum(rng.uniform(12.0, 22.0) for _ in range(n_rooms))
    aspect = rng.uniform(1.1, 1.6)
    W = float(np.sqrt(area * aspect))
    H = float(area / W)
    rects: list[tuple[float, float, float, float]] = []
    corridor = None
    if n_rooms >= 5:
        # a corridor strip across the middle; rooms on both sides
        cy = float(rng.uniform(0.4, 0.6) * H)
        H += CORRIDOR_WIDTH
        corridor = (0.0, cy, W, cy + CORRIDOR_WIDTH)
        n_a = (n_rooms - 1) // 2
        n_b = n_rooms - 1 - n_a
        rects += _bsp(rng, (0.0, 0.0, W, cy), n_a, [])
        rects += _bsp(rng, (0.0, cy + CORRIDOR_WIDTH, W, H), n_b, [])
    else:
        rects += _bsp(rng, (0.0, 0.0, W, H), n_rooms, [])
    kinds = ["living", "kitchen", "bedroom", "bedroom", "office", "bedroom", "living", "kitchen"]
    rooms = [Room(i, *r, kinds[i % len(kinds)]) for i, r in enumerate(rects)]
    if corridor is not None:
        rooms.append(Room(len(rooms), *corridor, "corridor"))
    # doors: a spanning tree over room adjacency (corridor first), plus a few extra loops
    n = len(rooms)
    adj = {}
    for i in range(n):
        for j in range(i + 1, n):
            s = _shared(rooms[i], rooms[j])
            if s is not None and s[3] - s[2] >= DOOR_WIDTH + 0.5:
                adj[(i, j)] = s
    connected = {n - 1 if corridor is not None else 0}
    doors = []
    edges = list(adj.items())
    rng.shuffle(edges)
    while len(connected) < n:
        for (i, j), s in edges:
            if (i in connected) != (j in connected):
                doors.append(_door_on(rng, s))
                connected |= {i, j}
                break
        else:
            raise RuntimeError("room layout is not connected")  # cannot happen for a BSP tiling
    for (i, j), s in edges[: max(0, n // 3)]:
        d = _door_on(rng, s)
        if all(not (d[0] == e[0] and abs(d[1] - e[1]) < 1e-6 and d[2] < e[3] and e[2] < d[3]) for e in doors):
            doors.append(d)
    return rooms, doors


def _door_on(rng, s) -> tuple[str, float, float, float]:
    axis, c, lo, hi = s
    a = float(rng.uniform(lo + 0.25, hi - 0.25 - DOOR_WIDTH))
    return (axis, c, a, a + DOOR_WIDTH)


def _wall_segments(rooms: list[Room], doors) -> list[tuple[str, float, float, float]]:
    """Merged room edges minus door gaps, as (axis, coord, lo, hi)."""
    lines: dict[tuple[str, float], list[tuple[float, float]]] = {}
    for r in rooms:
        for axis, c, lo, hi in (("x", r.x0, r.y0, r.y1), ("x", r.x1, r.y0, r.y1), ("y", r.y0, r.x0, r.x1),
                                ("y", r.y1, r.x0, r.x1)):
            lines.setdefault((axis, round(c, 6)), []).append((lo, hi))
    segs = []
    for (axis, c), ivs in lines.items():
        ivs.sort()
        merged = [list(ivs[0])]
        for lo, hi in ivs[1:]:
            if lo <= merged[-1][1] + 1e-6:
                merged[-1][1] = max(merged[-1][1], hi)
            else:
                merged.append([lo, hi])
        cuts = sorted((d[2], d[3]) for d in doors if d[0] == axis and abs(d[1] - c) < 1e-6)
        for lo, hi in merged:
            cur = lo
            for dlo, dhi in cuts:
                if dhi <= cur or dlo >= hi:
                    continue
                if dlo > cur:
                    segs.append((axis, c, cur, dlo))
                cur = max(cur, dhi)
            if hi > cur + 1e-6:
                segs.append((axis, c, cur, hi))
    return segs


# ---------------------------------------------------------------------------------------------
# furniture
# ---------------------------------------------------------------------------------------------

def _box(size, center) -> trimesh.Trimesh:
    b = trimesh.creation.box(extents=size)
    b.apply_translation(center)
    return b


def _furniture_parts(cls: str, rng: np.random.Generator) -> tuple[list[tuple[trimesh.Trimesh, int]], np.ndarray]:
    """Local-frame parts (mesh, material slot 0/1/2) of one object, footprint centred at the origin,
    resting on z = 0, facing -y. Returns the parts and the (w, d, h) extents."""
    P: list[tuple[trimesh.Trimesh, int]] = []
    if cls == "chair":
        w, d, sh = rng.uniform(0.42, 0.55), rng.uniform(0.42, 0.55), rng.uniform(0.42, 0.5)
        P.append((_box((w, d, 0.06), (0, 0, sh)), 0))
        for sx in (-1, 1):
            for sy in (-1, 1):
                P.append((_box((0.05, 0.05, sh), (sx * (w / 2 - 0.03), sy * (d / 2 - 0.03), sh / 2)), 1))
        bh = rng.uniform(0.35, 0.55)
        P.append((_box((w, 0.06, bh), (0, d / 2 - 0.03, sh + bh / 2)), 0))
        h = sh + bh
    elif cls == "sofa":
        w, d = rng.uniform(1.5, 2.2), rng.uniform(0.8, 0.95)
        P.append((_box((w, d, 0.42), (0, 0, 0.21)), 0))
        P.append((_box((w, 0.2, 0.45), (0, d / 2 - 0.1, 0.42 + 0.225)), 0))
        for sx in (-1, 1):
            P.append((_box((0.18, d, 0.25), (sx * (w / 2 - 0.09), 0, 0.42 + 0.125)), 1))
        for k in range(2):
            P.append((_box((w / 2 - 0.2, d - 0.3, 0.1), ((k - 0.5) * (w / 2 - 0.15), -0.08, 0.47)), 2))
        h = 0.87
    elif cls == "table":
        w, d, h = rng.uniform(0.9, 1.6), rng.uniform(0.7, 1.0), rng.uniform(0.72, 0.78)
        P.append((_box((w, d, 0.05), (0, 0, h - 0.025)), 0))
        for sx in (-1, 1):
            for sy in (-1, 1):
                P.append((_box((0.06, 0.06, h - 0.05), (sx * (w / 2 - 0.06), sy * (d / 2 - 0.06), (h - 0.05) / 2)), 1))
    elif cls == "tv_monitor":
        w, sh = rng.uniform(0.8, 1.3), rng.uniform(0.5, 0.75)
        P.append((_box((w + 0.3, 0.42, 0.5), (0, 0.05, 0.25)), 1))  # low cabinet under the screen
        P.append((_box((0.2, 0.15, 0.08), (0, 0.05, 0.54)), 2))
        P.append((_box((0.05, 0.05, 0.12), (0, 0.08, 0.64)), 2))
        P.append((_box((w, 0.05, sh), (0, 0.08, 0.7 + sh / 2)), 0))
        d, h = 0.42, 0.7 + sh
        w = w + 0.3
    elif cls == "plant":
        r, ph = rng.uniform(0.14, 0.25), rng.uniform(0.25, 0.45)
        pot = trimesh.creation.cylinder(radius=r, height=ph, sections=20)
        pot.apply_translation((0, 0, ph / 2))
        P.append((pot, 1))
        fr = rng.uniform(0.3, 0.45)
        for k in range(int(rng.integers(2, 5))):
            leaf = trimesh.creation.icosphere(subdivisions=1, radius=fr * rng.uniform(0.6, 1.0))
            off = rng.uniform(-0.12, 0.12, 2)
            leaf.apply_translation((off[0], off[1], ph + fr * (0.6 + 0.5 * k)))
            P.append((leaf, 0))
        w = d = 2 * max(r, fr)
        h = ph + fr * (1.6 + 0.5 * (len(P) - 2))
    elif cls == "bed":
        w, d = rng.uniform(1.0, 1.8), rng.uniform(1.9, 2.1)
        P.append((_box((w, d, 0.3), (0, 0, 0.15)), 1))
        P.append((_box((w - 0.05, d - 0.1, 0.2), (0, -0.03, 0.4)), 0))
        P.append((_box((w, 0.08, 1.0), (0, d / 2 - 0.04, 0.5)), 1))
        for k in range(2 if w > 1.3 else 1):
            P.append((_box((0.5, 0.35, 0.12), ((k - 0.5) * 0.6 if w > 1.3 else 0, d / 2 - 0.3, 0.56)), 2))
        h = 1.0
    elif cls == "cabinet":
        w, d, h = rng.uniform(0.5, 1.2), rng.uniform(0.35, 0.55), rng.uniform(0.7, 1.9)
        P.append((_box((w, d, h), (0, 0, h / 2)), 0))
        P.append((_box((0.04, 0.03, 0.15), (w / 4, -d / 2 - 0.015, h * 0.6)), 1))
    elif cls == "lamp":
        hh = rng.uniform(1.2, 1.7)
        pole = trimesh.creation.cylinder(radius=0.025, height=hh, sections=10)
        pole.apply_translation((0, 0, hh / 2))
        base = trimesh.creation.cylinder(radius=0.16, height=0.04, sections=16)
        base.apply_translation((0, 0, 0.02))
        shade = trimesh.creation.cone(radius=0.22, height=0.3, sections=16)
        shade.apply_translation((0, 0, hh - 0.1))
        P += [(pole, 1), (base, 1), (shade, 0)]
        w = d = 0.44
        h = hh + 0.2
    elif cls == "shelf":
        w, d, h = rng.uniform(0.6, 1.2), rng.uniform(0.28, 0.4), rng.uniform(1.0, 2.0)
        for sx in (-1, 1):
            P.append((_box((0.03, d, h), (sx * (w / 2 - 0.015), 0, h / 2)), 0))
        for k in range(int(h / 0.4) + 1):
            P.append((_box((w, d, 0.03), (0, 0, min(h - 0.015, 0.015 + k * 0.4))), 0))
        for k in range(int(h / 0.4)):
            P.append((_box((rng.uniform(0.15, w - 0.1), d * 0.7, 0.25), (rng.uniform(-0.1, 0.1), 0, 0.03 + k * 0.4 + 0.125)), 1))
    else:
        raise ValueError(f"unknown object class {cls!r}; known: {GOAL_CLASSES + DISTRACTOR_CLASSES}")
    return P, np.array([w, d, h], float)


ROOM_CLASSES = {
    "living": ["sofa", "tv_monitor", "table", "plant", "chair", "chair", "lamp", "shelf"],
    "bedroom": ["bed", "plant", "chair", "cabinet", "lamp", "tv_monitor"],
    "kitchen": ["table", "chair", "chair", "chair", "plant", "cabinet"],
    "office": ["table", "chair", "tv_monitor", "shelf", "plant", "sofa"],
    "corridor": ["plant", "cabinet"],
}


# ---------------------------------------------------------------------------------------------
# assembly
# ---------------------------------------------------------------------------------------------

class _Builder:
    def __init__(self):
        self.verts: list[np.ndarray] = []
        self.faces: list[np.ndarray] = []
        self.mat: list[np.ndarray] = []
        self.inst: list[np.ndarray] = []
        self.cls: list[np.ndarray] = []
        self.n = 0

    def add(self, mesh: trimesh.Trimesh, material: int, instance: int, class_id: int) -> None:
        v = np.asarray(mesh.vertices, np.float32)
        f = np.asarray(mesh.faces, np.int32) + self.n
        self.verts.append(v)
        self.faces.append(f)
        k = len(f)
        self.mat.append(np.full(k, material, np.int32))
        self.inst.append(np.full(k, instance, np.int32))
        self.cls.append(np.full(k, class_id, np.int32))
        self.n += len(v)

    def quad(self, corners, material, instance, class_id) -> None:
        self.add(trimesh.Trimesh(np.asarray(corners, float), [[0, 1, 2], [0, 2, 3]], process=False), material,
                 instance, class_id)


def make_house(seed: int, n_rooms: int | None = None, *, objects_per_room: tuple[int, int] = (2, 5),
               distractors: bool = True, identical_furniture: bool = False) -> House:
    """Build a procedural house, deterministic per ``seed``.

    Args:
        seed: any non-negative integer.
        n_rooms: 3..8 rooms, counting the corridor that houses of 5+ rooms get; random in that
            range when None.
        objects_per_room: (min, max) furniture pieces per non-corridor room.
        distractors: add cabinets, lamps and shelves (never goals).
        identical_furniture: every piece of a class is the same model (shape and three
            materials), as a house furnished from one catalogue (HM3D's matching dining chairs):
            instances of a class then differ only in where they stand and what surrounds them.
            Off: every instance has its own shape and materials.

    Raises:
        ValueError: for a negative seed or n_rooms outside 3..8.
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    rng = np.random.default_rng([int(seed), GENERATOR_VERSION])
    drawn = int(rng.integers(3, 9))  # always drawn, so make_house(s) == make_house(s, its own n_rooms)
    if n_rooms is None:
        n_rooms = drawn
    if isinstance(n_rooms, bool) or not isinstance(n_rooms, (int, np.integer)) or not 3 <= n_rooms <= 8:
        raise ValueError(f"n_rooms must be an integer in 3..8, got {n_rooms!r}")
    lo, hi = objects_per_room
    if not (0 <= lo <= hi):
        raise ValueError(f"objects_per_room must be (min, max) with 0 <= min <= max, got {objects_per_room!r}")
    rooms, doors = make_layout(rng, int(n_rooms))
    mats = MaterialTable()
    B = _Builder()
    next_inst = 1
    # floors and ceilings: one material per room
    for r in rooms:
        fm = random_material(rng, mats, kind="room")
        B.quad([(r.x0, r.y0, 0), (r.x1, r.y0, 0), (r.x1, r.y1, 0), (r.x0, r.y1, 0)], fm, next_inst, CLASS_IDS["floor"])
        next_inst += 1
        cm = mats.add([0.92, 0.92, 0.9], [0.85, 0.85, 0.83], "solid", 1.0, 0.03, int(rng.integers(0, 2**31 - 1)))
        B.quad([(r.x0, r.y0, WALL_HEIGHT), (r.x0, r.y1, WALL_HEIGHT), (r.x1, r.y1, WALL_HEIGHT), (r.x1, r.y0, WALL_HEIGHT)],
               cm, next_inst, CLASS_IDS["ceiling"])
        next_inst += 1
    # walls: one material per wall line segment, lintels above doors
    wall_mats = [random_material(rng, mats, kind="room") for _ in range(4)]
    for axis, c, a, b in _wall_segments(rooms, doors):
        size = (WALL_THICKNESS, b - a + WALL_THICKNESS, WALL_HEIGHT) if axis == "x" else (b - a + WALL_THICKNESS, WALL_THICKNESS, WALL_HEIGHT)
        center = (c, (a + b) / 2, WALL_HEIGHT / 2) if axis == "x" else ((a + b) / 2, c, WALL_HEIGHT / 2)
        B.add(_box(size, center), wall_mats[int(rng.integers(0, 4))], next_inst, CLASS_IDS["wall"])
        next_inst += 1
    for axis, c, a, b in doors:
        hgt = WALL_HEIGHT - DOOR_HEIGHT
        size = (WALL_THICKNESS, b - a, hgt) if axis == "x" else (b - a, WALL_THICKNESS, hgt)
        center = (c, (a + b) / 2, DOOR_HEIGHT + hgt / 2) if axis == "x" else ((a + b) / 2, c, DOOR_HEIGHT + hgt / 2)
        B.add(_box(size, center), wall_mats[0], next_inst, CLASS_IDS["wall"])
        next_inst += 1
    objects = _place_furniture(rng, rooms, doors, mats, B, next_inst, (lo, hi), distractors,
                               bool(identical_furniture))
    V = np.concatenate(B.verts).astype(np.float32)
    return House(
        seed=int(seed), vertices=V, faces=np.concatenate(B.faces).astype(np.int32),
        face_material=np.concatenate(B.mat), face_instance=np.concatenate(B.inst), face_class=np.concatenate(B.cls),
        vertex_colors=np.zeros_like(V), materials=mats, rooms=rooms, objects=objects, doors=list(doors),
        identical_furniture=bool(identical_furniture))


FREE_CELL = 0.1  # m, the placement grid


def _place_furniture(rng, rooms, doors, mats, B: _Builder, next_inst: int, per_room, distractors,
                     identical: bool = False) -> list[SceneObject]:
    """Place objects room by room on a coarse free grid, keeping doorways and a connected floor.
    ``identical``: the first piece of each class fixes its model (parts, extents, materials) for
    the rest of the house."""
    from scipy import ndimage

    xmax = max(r.x1 for r in rooms)
    ymax = max(r.y1 for r in rooms)
    nx, ny = int(np.ceil(xmax / FREE_CELL)) + 1, int(np.ceil(ymax / FREE_CELL)) + 1
    keepout = np.zeros((ny, nx), bool)  # door clearances: no object may stand there
    objs = np.zeros((ny, nx), bool)  # object footprints so far

    def mark(x0, y0, x1, y1, grid=keepout):
        i0, i1 = max(0, int(np.floor(y0 / FREE_CELL))), min(ny, int(np.ceil(y1 / FREE_CELL)))
        j0, j1 = max(0, int(np.floor(x0 / FREE_CELL))), min(nx, int(np.ceil(x1 / FREE_CELL)))
        grid[i0:i1, j0:j1] = True

    for axis, c, a, b in doors:
        if axis == "x":
            mark(c - 1.0, a - 0.2, c + 1.0, b + 0.2)
        else:
            mark(a - 0.2, c - 1.0, b + 0.2, c + 1.0)
    # where the robot centre may go: 0.25 m from walls (half thickness + radius + slack)
    clear = 0.25
    floor = np.zeros((ny, nx), bool)
    for r in rooms:
        mark(r.x0 + clear, r.y0 + clear, r.x1 - clear, r.y1 - clear, floor)
    door_cells = []
    for axis, c, a, b in doors:  # the passage through each doorway
        if axis == "x":
            mark(c - clear - 0.1, a + 0.22, c + clear + 0.1, b - 0.22, floor)
            door_cells.append((int(((a + b) / 2) / FREE_CELL), int(c / FREE_CELL)))
        else:
            mark(a + 0.22, c - clear - 0.1, b - 0.22, c + clear + 0.1, floor)
            door_cells.append((int(c / FREE_CELL), int(((a + b) / 2) / FREE_CELL)))
    door_rc = tuple(np.array(door_cells).T)
    objects: list[SceneObject] = []
    catalogue: dict[str, tuple] = {}  # class -> (parts, extents, material slots)

    def connected(blocked: np.ndarray) -> bool:
        """Doorways mutually reachable, and no free pocket of 0.2 m^2 or more cut off."""
        free = floor & (ndimage.distance_transform_edt(~blocked) * FREE_CELL > clear)
        lab, n = ndimage.label(free)
        ids = lab[door_rc]
        if ids.min() == 0 or not (ids == ids[0]).all():
            return False
        sizes = np.bincount(lab.ravel(), minlength=n + 1)
        sizes[0] = 0
        sizes[ids[0]] = 0
        return bool(sizes.max(initial=0) < 20)

    for r in rooms:
        pool = list(ROOM_CLASSES[r.kind])
        if not distractors:
            pool = [c for c in pool if c in GOAL_CLASSES]
        n_obj = int(rng.integers(per_room[0], per_room[1] + 1)) if r.kind != "corridor" else int(rng.integers(0, 2))
        for _ in range(n_obj):
            if not pool:
                break
            cls = pool.pop(int(rng.integers(0, len(pool))))
            if identical and cls in catalogue:
                parts, ext, slots = catalogue[cls]
            else:
                parts, ext = _furniture_parts(cls, rng)
                slots = [random_material(rng, mats) for _ in range(3)]
                catalogue[cls] = (parts, ext, slots)
            for _try in range(25):
                yaw_k = int(rng.integers(0, 4))
                w, d = (ext[0], ext[1]) if yaw_k % 2 == 0 else (ext[1], ext[0])
                if w > r.x1 - r.x0 - 0.4 or d > r.y1 - r.y0 - 0.4:
                    break
                cx = float(rng.uniform(r.x0 + 0.1 + w / 2, r.x1 - 0.1 - w / 2))
                cy = float(rng.uniform(r.y0 + 0.1 + d / 2, r.y1 - 0.1 - d / 2))
                trial = np.zeros_like(objs)
                mark(cx - w / 2, cy - d / 2, cx + w / 2, cy + d / 2, trial)
                if (trial & (objs | keepout)).any():
                    continue
                # every doorway must stay reachable from every other one
                if not connected(objs | trial):
                    continue
                objs |= trial
                ang = yaw_k * np.pi / 2
                T = trimesh.transformations.rotation_matrix(ang, (0, 0, 1))
                T[:3, 3] = (cx, cy, 0.0)
                for mesh, slot in parts:
                    m = mesh.copy()
                    m.apply_transform(T)
                    B.add(m, slots[slot], next_inst, CLASS_IDS[cls])
                objects.append(SceneObject(next_inst, cls, np.array([cx, cy, ext[2] / 2]), np.array([w, d, ext[2]]),
                                           float(ang), r.index))
                next_inst += 1
                break
    return objects
