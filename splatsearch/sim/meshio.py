"""House import/export as glTF binary (.glb), and import of a user's own mesh.

Export writes one glTF mesh per instance, named ``inst{ID:05d}_{class}``. Its faces carry baked
colours, so any viewer shows the house. The scene extras (``metadata["splatsearch"]``) hold the
procedural materials, the per-face material ids, the rooms and the objects, so a round trip
through :func:`load_house` is exact.

Foreign meshes (glb/gltf/obj/ply) with vertex or texture colours are imported with an
instance-id mapping: by node name (``names={"my_chair": (7, "chair")}``; names of the form
``inst{ID}_{class}`` map themselves), or by face (``face_instance`` (F,) plus ``classes={id: name}``
for a single mesh). Unmapped geometry becomes instance 0 of class "void": it is seen and it
blocks the way, but it is never a goal.
"""

from __future__ import annotations

import os
import re

import numpy as np
import trimesh

from splatsearch.io import atomic_write_bytes

from .house import CLASS_IDS, GENERATOR_VERSION, STRUCTURE_CLASSES, House, Room, SceneObject
from .materials import VERTEX_COLOR, MaterialTable

_NAME = re.compile(r"^inst(\d+)_([a-z_]+)")


def save_house(house: House, path: str) -> None:
    """Export ``house`` as .glb (atomically). See the module docstring for the layout."""
    if not str(path).lower().endswith(".glb"):
        raise ValueError(f"house export writes .glb files, got {path!r}")
    mats = house.materials.arrays()
    scene = trimesh.Scene()
    per_inst = {}
    class_names = {v: k for k, v in CLASS_IDS.items()}
    for inst in np.unique(house.face_instance):
        sel = np.flatnonzero(house.face_instance == inst)
        faces = house.faces[sel]
        verts = house.vertices[faces.reshape(-1)]  # unmerged: 3 vertices per face
        mesh = trimesh.Trimesh(verts, np.arange(len(verts)).reshape(-1, 3), process=False)
        fm = house.face_material[sel]
        col = np.where((fm >= 0)[:, None], mats["color_a"][np.maximum(fm, 0)] if len(mats["color_a"]) else 0,
                       house.vertex_colors[faces].mean(1))
        vcol = np.repeat(col, 3, axis=0)
        vcol[np.repeat(fm < 0, 3)] = house.vertex_colors[faces[fm < 0].reshape(-1)]
        mesh.visual.vertex_colors = np.c_[np.clip(vcol * 255, 0, 255), np.full(len(vcol), 255)].astype(np.uint8)
        cls = class_names[int(house.face_class[sel[0]])]
        name = f"inst{int(inst):05d}_{cls}"
        scene.add_geometry(mesh, node_name=name, geom_name=name)
        per_inst[name] = {"instance_id": int(inst), "class": cls, "face_material": fm.tolist(),
                          "face_class": house.face_class[sel].tolist()}
    scene.metadata["splatsearch"] = {
        "format": "splatsearch-house", "version": 1, "generator_version": GENERATOR_VERSION,
        "seed": house.seed, "wall_height": house.wall_height, "materials": house.materials.to_json(),
        "rooms": [vars(r) for r in house.rooms], "objects": [o.to_json() for o in house.objects],
        "doors": [list(d) for d in house.doors], "instances": per_inst,
        "identical_furniture": bool(house.identical_furniture),
    }
    atomic_write_bytes(path, scene.export(file_type="glb"))


def load_house(path: str, *, names: dict | None = None, face_instance: np.ndarray | None = None,
               classes: dict | None = None, z_up: bool = True) -> House:
    """Load a house written by :func:`save_house`, or a user's own mesh with an instance mapping.

    Args:
        path: .glb / .gltf / .obj / .ply file.
        names: node or geometry name -> (instance_id, class_name), for multi-mesh files.
        face_instance: (F,) instance id per face, for a single-mesh file.
        classes: instance_id -> class_name, with ``face_instance``.
        z_up: False for Y-up files (glTF's convention); they are rotated to Z-up.

    Raises:
        ValueError: unreadable file, unknown class names, or a mapping that does not fit the mesh.
    """
    if not os.path.exists(path):
        raise FileNotFoundError(path)
    try:
        loaded = trimesh.load(path, process=False, force="scene")
    except Exception as e:  # trimesh raises many types for corrupt files
        raise ValueError(f"{path}: cannot read mesh ({type(e).__name__}: {e})") from e
    meta = loaded.metadata.get("splatsearch") if isinstance(loaded.metadata, dict) else None
    if isinstance(meta, dict) and meta.get("format") == "splatsearch-house":
        return _load_own(loaded, meta)
    return _load_foreign(loaded, names or {}, face_instance, classes or {}, z_up, path)


def _geometries(scene: trimesh.Scene):
    """(node name, geometry name, mesh in world frame) for every geometry node."""
    for node in scene.graph.nodes_geometry:
        T, gname = scene.graph[node]
        g = scene.geometry[gname]
        if not isinstance(g, trimesh.Trimesh) or len(g.faces) == 0:
            continue
        m = g.copy()
        m.apply_transform(T)
        yield node, gname, m


def _load_own(scene: trimesh.Scene, meta: dict) -> House:
    V, F, FM, FI, FC = [], [], [], [], []
    n = 0
    for node, gname, m in _geometries(scene):
        info = meta["instances"].get(node) or meta["instances"].get(gname)
        if info is None:
            raise ValueError(f"geometry {node!r} is not described in the file's splatsearch metadata")
        if len(info["face_material"]) != len(m.faces):
            raise ValueError(f"geometry {node!r}: {len(m.faces)} faces but metadata for {len(info['face_material'])}")
        V.append(np.asarray(m.vertices, np.float32))
        F.append(np.asarray(m.faces, np.int32) + n)
        n += len(m.vertices)
        FM.append(np.asarray(info["face_material"], np.int32))
        FI.append(np.full(len(m.faces), info["instance_id"], np.int32))
        FC.append(np.asarray(info["face_class"], np.int32))
    verts = np.concatenate(V)
    return House(seed=meta.get("seed"), vertices=verts, faces=np.concatenate(F), face_material=np.concatenate(FM),
                 face_instance=np.concatenate(FI), face_class=np.concatenate(FC), vertex_colors=np.zeros_like(verts),
                 materials=MaterialTable.from_json(meta["materials"]), rooms=[Room(**r) for r in meta["rooms"]],
                 objects=[SceneObject.from_json(o) for o in meta["objects"]], wall_height=meta["wall_height"],
                 doors=[tuple(d) for d in meta["doors"]],
                 identical_furniture=bool(meta.get("identical_furniture", False)))


def _colors(m: trimesh.Trimesh) -> np.ndarray:
    """(V, 3) float colours of a mesh from vertex colours, face colours or a texture."""
    vis = m.visual
    try:
        if vis.kind == "texture":
            vis = vis.to_color()
        if vis.kind in ("vertex", "face"):
            return np.asarray(vis.vertex_colors, np.float32)[:, :3] / 255.0
    except Exception:  # a texture trimesh cannot sample: fall back to grey
        pass
    return np.full((len(m.vertices), 3), 0.7, np.float32)


def _check_class(name: str) -> str:
    if name not in CLASS_IDS:
        raise ValueError(f"unknown class {name!r}; known: {tuple(CLASS_IDS)}")
    return name


def _load_foreign(scene, names, face_instance, classes, z_up, path) -> House:
    geoms = list(_geometries(scene))
    if not geoms:
        raise ValueError(f"{path}: no triangle geometry")
    if face_instance is not None and len(geoms) != 1:
        raise ValueError("face_instance maps a single-mesh file; this file has several meshes (use names=)")
    V, F, C, FI, FC = [], [], [], [], []
    n = 0
    for node, gname, m in geoms:
        k = len(m.faces)
        if face_instance is not None:
            fi = np.asarray(face_instance, np.int64).reshape(-1)
            if fi.shape != (k,):
                raise ValueError(f"face_instance has {fi.size} entries but the mesh has {k} faces")
            fc = np.array([CLASS_IDS[_check_class(classes.get(int(i), "void"))] if i else 0 for i in fi], np.int32)
        else:
            inst, cls = 0, "void"
            key = node if node in names else gname if gname in names else None
            if key is not None:
                inst, cls = names[key]
            else:
                mt = _NAME.match(node) or _NAME.match(gname)
                if mt:
                    inst, cls = int(mt.group(1)), mt.group(2)
            fi = np.full(k, int(inst), np.int64)
            fc = np.full(k, CLASS_IDS[_check_class(cls)], np.int32)
        V.append(np.asarray(m.vertices, np.float32))
        F.append(np.asarray(m.faces, np.int32) + n)
        C.append(_colors(m))
        FI.append(fi.astype(np.int32))
        FC.append(fc)
        n += len(m.vertices)
    verts = np.concatenate(V)
    if not z_up:  # Y-up -> Z-up: (x, y, z) -> (x, -z, y)
        verts = np.stack([verts[:, 0], -verts[:, 2], verts[:, 1]], -1)
    faces = np.concatenate(F)
    fi = np.concatenate(FI)
    fc = np.concatenate(FC)
    objects = []
    class_names = {v: k for k, v in CLASS_IDS.items()}
    for inst in np.unique(fi[fi > 0]):
        if class_names[int(fc[fi == inst][0])] in STRUCTURE_CLASSES + ("void",):
            continue
        sel = faces[fi == inst].reshape(-1)
        lo, hi = verts[sel].min(0), verts[sel].max(0)
        objects.append(SceneObject(int(inst), class_names[int(fc[fi == inst][0])], (lo + hi) / 2, hi - lo, 0.0, -1))
    return House(seed=None, vertices=verts.astype(np.float32), faces=faces, face_material=np.full(len(faces), VERTEX_COLOR, np.int32),
                 face_instance=fi, face_class=fc, vertex_colors=np.concatenate(C).astype(np.float32),
                 materials=MaterialTable(), rooms=[], objects=objects, wall_height=float(verts[:, 2].max()))
