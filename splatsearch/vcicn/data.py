"""Training data for the VCICN: NVSM renders of object-local maps paired with ground truth.

For each goal-class object of a house (seeds from the training range, never the evaluation
houses), a scripted observer stands at random navigable places 0.8-3 m from the object, as the
robot does while it explores, and looks at it with the robot's level camera; each view that sees
the object goes into a real :class:`~splatsearch.search.local_map.ObservationStore` (the agent's
store, with its viewpoint-diversity rule). The object's local map is then built exactly as the
NVSM builds it (:func:`~splatsearch.search.local_map.build_local_map` of
:func:`~splatsearch.search.local_map.region_box`), the N_R hemisphere cameras that stand in free
space and see the object are rendered from it (RGB, accumulated opacity, expected depth, cropped
to the region as the NVSM crops), and the same cameras are ray-cast by the simulator (ground-truth
RGB and depth). A few goal-image-style cameras (the val-hard sampling: 0.5-2.5 m, 1-2 m high,
any angle in front of the object) are added so training also sees extreme viewpoints.

Renders are made at the robot camera's size (320 x 240 by default, the NVSM's size) and stored
downsampled by ``store_scale`` (area averaging) to keep shards small. One compressed ``.npz``
shard per house, written atomically; a finished shard is skipped on a rerun; everything is
seeded from the house seed, so a shard is reproducible.

Shard arrays (O objects, V views per object, h x w stored pixels):

==================  =====================  ===============================================
key                 shape, dtype           meaning
==================  =====================  ===============================================
``render``          (O, V, h, w, 3) uint8  local-map render, RGB
``alpha``           (O, V, h, w) uint8     accumulated opacity x 255
``render_depth``    (O, V, h, w) float16   expected depth (m), 0 where alpha < 0.05
``gt``              (O, V, h, w, 3) uint8  ray-cast ground truth, RGB
``gt_depth``        (O, V, h, w) float16   ray-cast depth (m), 0 = nothing within range
``viewmats``        (O, V, 4, 4) float32   world-to-camera of each view
``valid``           (O, V) bool            view exists (objects with fewer views are padded)
``goal_style``      (O, V) bool            a goal-image-style (val-hard) view, not hemisphere
``K``               (3, 3) float32         intrinsics at the stored size
``instance_ids``    (O,) int32             the objects
``n_obs``           (O,) int32             observations in each object's store
==================  =====================  ===============================================
"""

from __future__ import annotations

import io
import json
import os
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from splatsearch.agent.config import AgentConfig

#: evaluation houses start at splatsearch.evaluation.EVAL_SEED_BASE; training seeds stay below this
TRAIN_SEED_LIMIT = 500


@dataclass(frozen=True)
class DataConfig:
    """Settings of the training-data generator.

    Attributes:
        width, height: render size in pixels (the robot camera and the NVSM views).
        store_scale: stored images are downsampled by this factor (area averaging).
        n_views, view_radius (m), view_elevations_deg: the NVSM hemisphere (the agent's defaults).
        goal_views: goal-image-style (val-hard) cameras per object.
        max_objects: goal-class objects per house at most (chosen at random, seeded).
        min_obs, max_obs: observations per object (drawn uniformly), as the robot's store holds.
        obs_min_px: an observation must show this many pixels of the object.
        view_min_px: a hemisphere / goal-style view is kept when the object covers this many
            pixels in the ground truth (cameras behind walls are dropped).
        alpha_tau: opacity below which a rendered pixel is a hole (the agent's ``inpaint_tau``).
    """

    width: int = 320
    height: int = 240
    store_scale: int = 2
    # the NVSM's own camera settings, so training views match what the agent renders
    n_views: int = AgentConfig.n_views
    view_radius: float = AgentConfig.view_radius
    view_elevations_deg: tuple = AgentConfig.view_elevations_deg
    goal_views: int = 2
    max_objects: int = 4
    min_obs: int = 1
    max_obs: int = 5
    obs_min_px: int = 400
    view_min_px: int = 200
    alpha_tau: float = AgentConfig.inpaint_tau

    @property
    def views_per_object(self) -> int:
        return self.n_views + self.goal_views


def parse_houses(text: str) -> list[int]:
    """House seeds from ``"A-B"`` (inclusive), ``"A,B,C"`` or a mix (``"0-9,20"``). Seeds must be
    in the training range [0, TRAIN_SEED_LIMIT)."""
    seeds: list[int] = []
    for part in str(text).split(","):
        part = part.strip()
        if not part:
            continue
        a, sep, b = part.partition("-")
        try:
            lo, hi = int(a), int(b) if sep else int(a)
        except ValueError as e:
            raise ValueError(f"bad house range {part!r}; expected A-B or A,B,C (e.g. 0-39)") from e
        if hi < lo:
            raise ValueError(f"empty house range {part!r}")
        seeds.extend(range(lo, hi + 1))
    if not seeds:
        raise ValueError(f"no houses in {text!r}")
    bad = [s for s in seeds if not 0 <= s < TRAIN_SEED_LIMIT]
    if bad:
        raise ValueError(f"training houses must be seeds 0-{TRAIN_SEED_LIMIT - 1} (evaluation houses are 1000+, "
                         f"never trained on); got {bad[:5]}")
    return sorted(dict.fromkeys(seeds))


def shard_name(seed: int, identical_furniture: bool) -> str:
    return f"house_{seed:04d}{'_same' if identical_furniture else ''}.npz"


def _downsample(a: np.ndarray, s: int) -> np.ndarray:
    if s == 1:
        return a
    import cv2

    h, w = a.shape[:2]
    return cv2.resize(a, (w // s, h // s), interpolation=cv2.INTER_AREA)


def _u8(x: np.ndarray) -> np.ndarray:
    return (np.clip(x, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def render_views(gmap, viewmats: np.ndarray, K: np.ndarray, width: int, height: int,
                 crop_box: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The NVSM render of ``viewmats`` (V, 4, 4) with expected depth: the same rasterizer call as
    :func:`~splatsearch.search.novel_views.render_novel_views` (one camera per call, Gaussians
    outside ``crop_box`` hidden), in ``"RGB+ED"`` mode. Returns rgb (V, H, W, 3) in [0, 1],
    alpha (V, H, W), expected depth (V, H, W) metres (0 where alpha < 0.05)."""
    from splatsearch.rasterization import rasterize

    means, quats, scales, opac, colors = gmap.render_args()
    lo, hi = (np.asarray(b, np.float32).reshape(3) for b in crop_box)
    m = np.asarray(means)
    opac = np.asarray(opac) * np.all((m >= lo) & (m <= hi), axis=1)
    rgbs, alphas, depths = [], [], []
    for vm in np.asarray(viewmats, np.float32):
        out = rasterize(means, quats, scales, opac, colors, vm, K, width, height, render_mode="RGB+ED",
                        near_plane=0.01)
        a = np.asarray(out.alpha)[..., 0]
        rgbs.append(np.asarray(out.image))
        alphas.append(a)
        depths.append(np.where(a >= 0.05, np.asarray(out.depth)[..., 0], 0.0))
    return (np.clip(np.stack(rgbs), 0, 1).astype(np.float32), np.stack(alphas).astype(np.float32),
            np.stack(depths).astype(np.float32))


def _observations(env, obj, rng: np.random.Generator, n: int, cfg: DataConfig):
    """Up to ``n`` level robot-camera views of ``obj`` from navigable cells 0.8-3 m away."""
    from splatsearch.sim.env import CAMERA_HEIGHT, camera_viewmat

    nav = env.nav
    cells = np.argwhere(nav.navigable)
    xy = nav.cell_to_world(cells)
    d = np.hypot(xy[:, 0] - obj.center[0], xy[:, 1] - obj.center[1])
    cand = np.flatnonzero((d >= 0.8) & (d <= 3.0))
    out = []
    for _ in range(40 if len(cand) else 0):
        if len(out) >= n:
            break
        p = xy[rng.choice(cand)]
        yaw = np.arctan2(obj.center[1] - p[1], obj.center[0] - p[0]) + rng.uniform(-0.35, 0.35)
        vm = camera_viewmat(p[0], p[1], yaw, CAMERA_HEIGHT)
        f = env.renderer.render(vm, env.K, cfg.width, cfg.height, max_depth=env.max_depth)
        if np.count_nonzero(f.instance == obj.instance_id) >= cfg.obs_min_px:
            out.append(f)
    return out


def _goal_style_cameras(env, obj, rng: np.random.Generator, n: int, cfg: DataConfig) -> list[np.ndarray]:
    from splatsearch.sim.episodes import sample_goal_camera

    cams = []
    for _ in range(n):
        try:
            cams.append(sample_goal_camera(env, obj, "val-hard", rng, cfg.width, cfg.height, tries=60))
        except RuntimeError:
            break
    return cams


def object_sample(env, obj, rng: np.random.Generator, cfg: DataConfig, *, map_seed: int = 0) -> dict | None:
    """One object's views: render / ground-truth pairs at the render size (not downsampled).

    Returns None when the object is not seen well enough from anywhere. Keys as in the module
    docstring, without the object axis, plus ``"K"``; images are float32 in [0, 1].
    """
    from splatsearch.search.local_map import LocalMapConfig, ObservationStore, build_local_map, region_box
    from splatsearch.search.novel_views import hemisphere_viewpoints

    lm = LocalMapConfig()
    n_obs = int(rng.integers(cfg.min_obs, cfg.max_obs + 1))
    frames = _observations(env, obj, rng, n_obs, cfg)
    if not frames:
        return None
    store = ObservationStore(lm.max_frames, lm.min_separation)
    for f in frames:
        store.add(0, f.rgb, f.depth, f.viewmat)
    # the agent's entry extent is a robust percentile box of its lifted masks; the true box with
    # a few centimetres of noise stands in for it
    half = 0.5 * np.asarray(obj.size, np.float64)
    bmin = obj.center - half + rng.normal(0, 0.03, 3)
    bmax = obj.center + half + rng.normal(0, 0.03, 3)
    centroid = 0.5 * (bmin + bmax)
    lo, hi = region_box(bmin, np.maximum(bmax, bmin), lm.margin)
    gmap = build_local_map(store[0], env.K, cfg.width, cfg.height, lo, hi, lm, seed=map_seed)
    az0 = float(rng.uniform(0, 360))
    cams = list(hemisphere_viewpoints(centroid, cfg.view_radius, cfg.n_views, cfg.view_elevations_deg, az0))
    goal_style = [False] * len(cams)
    g = _goal_style_cameras(env, obj, rng, cfg.goal_views, cfg)
    cams += g
    goal_style += [True] * len(g)
    # the cameras are stored as float32: both renders use exactly the stored camera
    cams = [np.asarray(c, np.float32).astype(np.float64) for c in cams]
    gts, keep = [], []
    for vm in cams:
        f = env.renderer.render(vm, env.K, cfg.width, cfg.height, max_depth=env.max_depth)
        ok = np.count_nonzero(f.instance == obj.instance_id) >= cfg.view_min_px
        keep.append(ok)
        if ok:
            gts.append(f)
    if sum(keep[:cfg.n_views]) < 2:
        return None
    vms = np.stack([c for c, k in zip(cams, keep) if k]).astype(np.float32)
    rgb, alpha, depth = render_views(gmap, vms, env.K, cfg.width, cfg.height, (lo, hi))
    return {"render": rgb, "alpha": alpha, "render_depth": depth,
            "gt": np.stack([f.rgb for f in gts]).astype(np.float32),
            "gt_depth": np.stack([f.depth for f in gts]).astype(np.float32),
            "viewmats": vms, "goal_style": np.array([s for s, k in zip(goal_style, keep) if k]),
            "K": np.asarray(env.K, np.float32), "n_obs": len(store[0]), "instance_id": obj.instance_id}


def house_shard(seed: int, identical_furniture: bool, cfg: DataConfig) -> dict[str, np.ndarray]:
    """The arrays of one house's shard (see the module docstring); deterministic for its seed."""
    from splatsearch import sim

    house = sim.make_house(seed, identical_furniture=identical_furniture)
    env = sim.HouseEnv(house, width=cfg.width, height=cfg.height)
    rng = np.random.default_rng([int(seed), int(identical_furniture), 23])
    objs = house.goal_objects()
    order = rng.permutation(len(objs))[:cfg.max_objects]
    s, V = cfg.store_scale, cfg.views_per_object
    h, w = cfg.height // s, cfg.width // s
    samples = []
    for i in order:
        smp = object_sample(env, objs[int(i)], rng, cfg, map_seed=int(seed))
        if smp is not None:
            samples.append(smp)
    O = len(samples)
    out = {"render": np.zeros((O, V, h, w, 3), np.uint8), "alpha": np.zeros((O, V, h, w), np.uint8),
           "render_depth": np.zeros((O, V, h, w), np.float16), "gt": np.zeros((O, V, h, w, 3), np.uint8),
           "gt_depth": np.zeros((O, V, h, w), np.float16), "viewmats": np.tile(np.eye(4, dtype=np.float32), (O, V, 1, 1)),
           "valid": np.zeros((O, V), bool), "goal_style": np.zeros((O, V), bool),
           "instance_ids": np.array([smp["instance_id"] for smp in samples], np.int32),
           "n_obs": np.array([smp["n_obs"] for smp in samples], np.int32)}
    Ks = np.asarray(env.K, np.float32).copy()
    Ks[:2] /= s
    out["K"] = Ks
    for o, smp in enumerate(samples):
        n = len(smp["viewmats"])
        out["valid"][o, :n] = True
        out["goal_style"][o, :n] = smp["goal_style"]
        out["viewmats"][o, :n] = smp["viewmats"]
        for v in range(n):
            out["render"][o, v] = _u8(_downsample(smp["render"][v], s))
            out["alpha"][o, v] = _u8(_downsample(smp["alpha"][v], s))
            out["gt"][o, v] = _u8(_downsample(smp["gt"][v], s))
            # nearest sampling for depth: averaging across an edge invents surfaces
            out["render_depth"][o, v] = smp["render_depth"][v][::s, ::s]
            out["gt_depth"][o, v] = smp["gt_depth"][v][::s, ::s]
    out["seed"] = np.int32(seed)
    out["identical_furniture"] = np.bool_(identical_furniture)
    out["config"] = np.frombuffer(json.dumps(asdict(cfg)).encode(), np.uint8)
    return out


def _write_shard(path: str, arrays: dict[str, np.ndarray]) -> int:
    from splatsearch.io import atomic_write_bytes

    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    data = buf.getvalue()
    atomic_write_bytes(path, data)
    return len(data)


def _shard_job(seed: int, identical: bool, cfg_json: str, path: str) -> dict:
    """A worker job: make and write one shard; returns its statistics."""
    cfg = DataConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in json.loads(cfg_json).items()})
    t0 = time.perf_counter()
    arrays = house_shard(seed, identical, cfg)
    nbytes = _write_shard(path, arrays)
    return {"seed": seed, "identical_furniture": identical, "objects": int(len(arrays["instance_ids"])),
            "views": int(arrays["valid"].sum()), "bytes": nbytes, "seconds": time.perf_counter() - t0}


def generate(seeds: Sequence[int], out_dir: str, *, furniture: str = "both", cfg: DataConfig | None = None,
             workers: int = 1, progress: bool = True) -> dict:
    """Write one shard per (house, furniture mode) to ``out_dir``; skips shards that exist.

    Args:
        seeds: training house seeds (see :func:`parse_houses`).
        furniture: "default", "identical" or "both" (each house twice).
        workers: local worker processes (1 = in this process).

    Returns a report: shards written and skipped, objects, views, MB, seconds.
    """
    from splatsearch.parallel import Job, make_executor, warm_worker

    cfg = cfg or DataConfig()
    if furniture not in ("default", "identical", "both"):
        raise ValueError(f"furniture must be 'default', 'identical' or 'both', got {furniture!r}")
    modes = {"default": [False], "identical": [True], "both": [False, True]}[furniture]
    bad = [s for s in seeds if not 0 <= s < TRAIN_SEED_LIMIT]
    if bad:
        raise ValueError(f"training houses must be seeds 0-{TRAIN_SEED_LIMIT - 1}; got {bad[:5]}")
    os.makedirs(out_dir, exist_ok=True)
    cfg_json = json.dumps(asdict(cfg))
    todo, skipped = [], 0
    for sd in seeds:
        for same in modes:
            path = os.path.join(out_dir, shard_name(sd, same))
            if os.path.exists(path):
                skipped += 1
                continue
            todo.append((sd, same, path))
    from splatsearch.kernels.parallel import cpu_threads

    threads = max(1, cpu_threads() // max(1, workers))
    jobs = [Job(os.path.basename(p), _shard_job, (sd, same, cfg_json, p)) for sd, same, p in todo]
    report = {"shards_written": 0, "shards_skipped": skipped, "objects": 0, "views": 0, "bytes": 0, "errors": [],
              "seconds": 0.0, "seconds_per_object": None}
    t0 = time.perf_counter()
    bar = None
    if progress and jobs:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

        bar = Progress(TextColumn("vcicn data"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[info]}"),
                       TimeElapsedColumn(), TimeRemainingColumn())
        bar.start()
        task = bar.add_task("shards", total=len(jobs), info="")
    try:
        with make_executor("local", workers, warmup=warm_worker,
                           warmup_args=(threads, ("splatsearch.search.local_map", "splatsearch.sim"))) as ex:
            for o in ex.run(jobs):
                if o.ok:
                    st = o.value
                    report["shards_written"] += 1
                    report["objects"] += st["objects"]
                    report["views"] += st["views"]
                    report["bytes"] += st["bytes"]
                else:
                    report["errors"].append(f"{o.key}: {o.error.strip().splitlines()[-1] if o.error else 'lost'}")
                if bar:
                    bar.update(task, advance=1, info=f"{report['objects']} objects, {report['views']} views, "
                                                     f"{report['bytes'] / 1e6:.0f} MB")
    finally:
        if bar:
            bar.stop()
    report["seconds"] = time.perf_counter() - t0
    if report["objects"]:
        report["seconds_per_object"] = report["seconds"] * max(1, workers) / report["objects"]
    report["MB"] = report.pop("bytes") / 1e6
    return report


def list_shards(data_dir: str) -> list[str]:
    """The shard files in ``data_dir``, sorted."""
    if not os.path.isdir(data_dir):
        raise FileNotFoundError(f"training data folder not found: {data_dir!r} (make it with `splatsearch vcicn data`)")
    names = sorted(n for n in os.listdir(data_dir) if n.startswith("house_") and n.endswith(".npz"))
    if not names:
        raise FileNotFoundError(f"no house_*.npz shards in {data_dir!r} (make them with `splatsearch vcicn data`)")
    return [os.path.join(data_dir, n) for n in names]


def shard_seed(path: str) -> int:
    """The house seed in a shard's file name."""
    return int(os.path.basename(path).split("_")[1].split(".")[0])
