"""Store the NVSM views of look-alike-house episodes, for matcher and completion studies (issue 23).

    python benchmarks/nvsm_views.py --set dev  --episodes 8 --out runs/nvsm_views/dev
    python benchmarks/nvsm_views.py --set eval --episodes 8 --out runs/nvsm_views/eval

Each episode runs the SplatSearch agent (variant ``splatsearch``, identifying by feature matches
alone: ``colour_cue=False``, as ``splatsearch eval --identical-furniture --no-appearance``) in a
house built with ``identical_furniture=True``, and records every NVSM run
(:meth:`splatsearch.agent.Verifier.verify`): the object-local map's raw renders (the flat grey
background already filled, as the matcher sees them), their opacity, the interior hole masks the
completion step fills, the background masks, the cameras, and the OpenCV-inpainted views.
Same-class objects the agent observed but never ran the NVSM on (it stops once it reaches what it
takes for the goal) are then verified the same way (their stored observations, ``build_local_map``
and ``verify_object``, through the agent's own ``Verifier.verify``), so that every episode has
look-alikes with views.

Sets: ``dev`` samples val-hard episodes in houses ``--first-house`` onward (seeds < 1000, for
tuning); ``eval`` takes the episodes of ``splatsearch eval --split val-hard --seed 0
--identical-furniture`` (houses 1000+, never tuned on) in their order. Episodes whose goal has no
other instance of its class in the house are skipped (nothing to separate it from); the skipped
ids are listed in ``OUT/manifest.json``.

One ``OUT/ep_<house>_<id>.npz`` per episode, written atomically; an episode whose file exists is
not run again (resumable). Arrays (V = all views of all runs, R = runs):

=====================  =================  ==================================================
key                    shape / dtype      meaning
=====================  =================  ==================================================
goal                   (Hg, Wg, 3) uint8  the goal image
K                      (3, 3) float64     NVSM camera intrinsics (pixels); width, height
rendered               (V, H, W, 3) uint8 raw renders (background filled grey)
alpha                  (V, H, W) uint8    accumulated opacity x 255
holes                  (V, H, W) bool     interior holes (what an inpainter fills)
background             (V, H, W) bool     region outside the object's box, filled flat
opencv                 (V, H, W, 3) uint8 ``OpenCVInpainter()`` of rendered / holes
viewmats               (V, 4, 4) float64  world-to-camera of each view
view_run               (V,) int64         run index of each view
run_entry              (R,) int64         object-DB entry id
run_instance           (R,) int64         simulator instance it maps to (nearest of its class)
run_instance_dist      (R,) float64       metres from the entry centroid to that instance
run_is_goal            (R,) bool          the instance is the episode's goal
run_source             (R,) str           "agent" (during the search) or "supplement"
run_agent_counts_max   (R,) int64         the agent's own e_max of that run (its matcher)
run_bbox_min/_max      (R, 3) float64     the entry's extent (metres) when it was verified
run_centroid           (R, 3) float64     the entry's centroid (metres)
obs_rgb                (F, H, W, 3) uint8 the stored observations the run's local map was built
obs_depth              (F, H, W) uint16   from (depth in millimetres, 0 invalid), for
obs_viewmat            (F, 4, 4) float64  ``benchmarks/nvsm_rerender.py``
obs_run                (F,) int64         run index of each observation
xobs_*                 as obs_*           the same from a shadow store of ``SHADOW_FRAMES``
                                          observations per object (more keyframes; the agent
                                          itself used only obs_*)
local                  (V, H, W, 3) uint8 the local map's renders over black (before any fill)
grgb, galpha           (V, H, W, 3), (V,  the agent's online map (whole house) rendered from
                       H, W) uint8        the same cameras at verification time, uncropped
gcrgb, gcalpha         as grgb, galpha    the same cropped to the local map's region box
episode                () str             the episode as JSON; meta: () str JSON of settings
=====================  =================  ==================================================
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import sys
import time

import numpy as np

#: views of a run are stored at this alpha quantisation (1/255)
_U8 = 255.0


def _u8(img: np.ndarray) -> np.ndarray:
    """float [0, 1] -> uint8 with the rounding the matchers use (so counts do not change)."""
    return (np.clip(np.asarray(img, np.float32), 0, 1) * 255 + 0.5).astype(np.uint8)


def dev_episodes(n: int, first_house: int = 0, per_house: int = 5, seed: int = 0) -> list:
    """``n`` val-hard episodes in look-alike houses ``first_house, first_house + 1, ...`` (all
    < :data:`splatsearch.evaluation.EVAL_SEED_BASE`), sampled as the evaluation samples its own."""
    from splatsearch import sim
    from splatsearch.evaluation import EVAL_SEED_BASE

    eps = []
    hs = first_house
    while len(eps) < n:
        if hs >= EVAL_SEED_BASE:
            raise ValueError(f"dev houses must stay below {EVAL_SEED_BASE}")
        house = sim.make_house(hs, identical_furniture=True)
        for e in sim.make_episodes(house, min(per_house, n - len(eps)), "val-hard", seed=seed, env=sim.HouseEnv(house)):
            e.episode_id = len(eps)
            eps.append(e)
        hs += 1
    return eps


def eval_episodes(n: int, seed: int = 0) -> list:
    """The first ``n`` episodes of ``splatsearch eval --split val-hard --seed SEED --identical-furniture``."""
    from splatsearch.evaluation import make_eval_episodes

    return make_eval_episodes("val-hard", n, seed, identical_furniture=True)


def has_lookalike(house, ep) -> bool:
    """Whether the house holds another instance of the goal's class."""
    return sum(o.class_name == ep.goal_class for o in house.objects) >= 2


def _nearest_instance(house, label: str, centroid) -> tuple[int, float]:
    objs = [o for o in house.objects if o.class_name == label]
    if not objs:
        return -1, float("inf")
    d = [float(np.linalg.norm(np.asarray(o.center[:2]) - np.asarray(centroid)[:2])) for o in objs]
    i = int(np.argmin(d))
    return int(objs[i].instance_id), d[i]


def split_views(rendered: np.ndarray, holes: np.ndarray, alpha: np.ndarray, alpha_tau: float,
                fill: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The stored form of one NVSM run's views, whatever completion the agent used: (rendered
    (V, H, W, 3) with the background flat ``fill``, interior holes (V, H, W), background
    (V, H, W)). The NVSM hands a learned completion (``completes_background``) every hole and
    leaves the background black; for raw and OpenCV views it splits the border-connected holes
    off and greys them, which is done here, so that the ``raw`` and ``opencv`` rows of
    ``nvsm_separation.py`` are the NVSM's own whichever inpainter the dumping agent ran."""
    from splatsearch.search.inpainting import split_holes

    interior, outside = split_holes(np.asarray(holes, bool))
    out = np.array(rendered, np.float32)
    out[outside] = fill
    return out, interior, ((np.asarray(alpha) < alpha_tau) & ~interior) | outside


#: observations per object the shadow store keeps (the agent keeps ``LocalMapConfig.max_frames``)
SHADOW_FRAMES = 10


@contextlib.contextmanager
def shadow_observations(max_frames: int = SHADOW_FRAMES):
    """Yield an :class:`ObservationStore` of ``max_frames`` per object that receives every
    observation the agent's own store receives (inside the ``with`` block, this process only), so
    that local maps from more keyframes can be built later without changing what the agent does."""
    from splatsearch.search.local_map import ObservationStore

    shadow = ObservationStore(max_frames)
    orig = ObservationStore.add

    def add(self, entry_id, rgb, depth, viewmat):
        orig(self, entry_id, rgb, depth, viewmat)
        if self is not shadow:
            shadow.min_separation = self.min_separation
            orig(shadow, entry_id, rgb, depth, viewmat)

    ObservationStore.add = add
    try:
        yield shadow
    finally:
        ObservationStore.add = orig


@contextlib.contextmanager
def capturing_perception(holder: dict):
    """Put the agent's :class:`Perception` (its online map) into ``holder["perception"]`` when it
    is built (inside the ``with`` block, this process only)."""
    from splatsearch.agent import perception

    orig = perception.Perception.__init__

    def init(self, *a, **k):
        orig(self, *a, **k)
        holder["perception"] = self

    perception.Perception.__init__ = init
    try:
        yield
    finally:
        perception.Perception.__init__ = orig


def global_renders(gmap, viewmats, K, width: int, height: int, box) -> dict:
    """The online map ``gmap`` rendered from ``viewmats``: uint8 arrays ``grgb``/``galpha``
    (uncropped) and ``gcrgb``/``gcalpha`` (cropped to ``box``, the local map's region)."""
    from splatsearch.search.novel_views import render_novel_views

    rgb, alpha = render_novel_views(gmap, viewmats, K, width, height)
    crgb, calpha = render_novel_views(gmap, viewmats, K, width, height, crop_box=box)
    return {"grgb": _u8(rgb), "galpha": _u8(alpha), "gcrgb": _u8(crgb), "gcalpha": _u8(calpha)}


@contextlib.contextmanager
def recording_nvsm(runs: list, source: list, shadow=None, holder: dict | None = None):
    """Record every :meth:`Verifier.verify` that returns a result into ``runs`` (dicts with the
    entry, its centroid and label, the result, the renders' opacity and ``source[0]``).

    Patches ``Verifier.verify`` and the ``render_novel_views`` that ``verify_object`` calls, in
    this process only and only inside the ``with`` block (the renders' opacity is not part of
    the NVSM's result). With ``holder`` (see :func:`capturing_perception`) each run also gets
    the online map's renders of its cameras (:func:`global_renders`) under ``"global"``."""
    from splatsearch.agent import verification
    from splatsearch.search import object_search

    orig_verify, orig_render = verification.Verifier.verify, object_search.render_novel_views
    last_alpha: list = [None]

    def render(*a, **k):
        rgb, alpha = orig_render(*a, **k)
        last_alpha[0] = np.array(alpha, np.float32)
        return rgb, alpha

    def verify(self, db, entry_id, observations, occupancy=None, fill_map=None):
        from splatsearch.search.local_map import region_box

        last_alpha[0] = None
        score = orig_verify(self, db, entry_id, observations, occupancy, fill_map)
        if score is not None:
            e = db[entry_id]
            grend = None
            if holder is not None and holder.get("perception") is not None:
                box = region_box(e.bbox_min, e.bbox_max, self.cfg.local_map.margin)
                grend = global_renders(holder["perception"].mapper.map, score.viewmats, self.K, self.W, self.H, box)
            runs.append({"entry": int(entry_id), "label": e.label, "centroid": np.array(e.centroid, float),
                         "score": score, "alpha": last_alpha[0], "source": source[0],
                         "alpha_tau": float(self.nvsm_config.alpha_tau),
                         "crop_fill": float(self.nvsm_config.crop_fill),
                         "frames": [(f.rgb, f.depth, f.viewmat) for f in observations[entry_id]],
                         "xframes": [(f.rgb, f.depth, f.viewmat) for f in (shadow[entry_id] if shadow else [])],
                         "bbox": (np.array(e.bbox_min, float), np.array(e.bbox_max, float)),
                         "global": grend})
        return score

    verification.Verifier.verify, object_search.render_novel_views = verify, render
    try:
        yield
    finally:
        verification.Verifier.verify, object_search.render_novel_views = orig_verify, orig_render


def dump_episode(ep, path: str, *, max_steps: int | None = None, supplement: bool = True) -> dict:
    """Run ``ep`` with the agent, record its NVSM runs (and those of the same-class objects it
    observed but never verified) and write them to ``path`` (.npz, atomically). Returns a small
    summary dict (runs, objects, seconds)."""
    from splatsearch.agent import AgentConfig
    from splatsearch.episode import run_episode
    from splatsearch.io import atomic_write_bytes
    from splatsearch.search.inpainting import OpenCVInpainter
    from splatsearch.sim.env import HouseEnv
    from splatsearch.sim.episodes import goal_image, house_for_episode

    t0 = time.perf_counter()
    env = HouseEnv(house_for_episode(ep), width=ep.goal_width, height=ep.goal_height)
    cfg = AgentConfig(variant="splatsearch", colour_cue=False)
    runs: list = []
    source = ["agent"]
    holder: dict = {}

    def on_step(agent, _obs, _info):
        holder["agent"] = agent

    with capturing_perception(holder), shadow_observations() as shadow, recording_nvsm(runs, source, shadow, holder):
        res = run_episode(ep, cfg, env=env, on_step=on_step, max_steps=max_steps)
        agent = holder.get("agent")
        if supplement and agent is not None:
            source[0] = "supplement"
            done = {r["entry"] for r in runs}
            for e in list(agent.db):
                if e.id not in done and agent.perception.observations[e.id]:
                    agent.verifier.verify(agent.db, e.id, agent.perception.observations, agent.explorer.occupancy)
    t_agent = time.perf_counter() - t0
    goal = goal_image(env, ep).rgb
    inp = OpenCVInpainter()
    arrays: dict[str, list] = {k: [] for k in ("rendered", "alpha", "holes", "background", "opencv", "viewmats",
                                               "view_run", "obs_rgb", "obs_depth", "obs_viewmat", "obs_run", "xobs_rgb",
                                               "xobs_depth", "xobs_viewmat", "xobs_run", "local", "grgb",
                                               "galpha", "gcrgb", "gcalpha")}
    meta_runs: dict[str, list] = {k: [] for k in ("entry", "instance", "instance_dist", "is_goal", "source",
                                                  "agent_counts_max", "bbox_min", "bbox_max", "centroid")}
    for i, r in enumerate(runs):
        s = r["score"]
        holes = np.asarray(s.holes, bool)
        alpha = r["alpha"] if r["alpha"] is not None else np.where(holes, 0.0, 1.0)
        rendered, holes, background = split_views(np.asarray(s.rendered, np.float32), holes, alpha, r["alpha_tau"],
                                                  r.get("crop_fill", 0.5))
        arrays["rendered"].append(_u8(rendered))
        arrays["alpha"].append(_u8(alpha))
        arrays["holes"].append(holes)
        arrays["background"].append(background)
        arrays["opencv"].append(_u8(inp.inpaint(rendered, holes)))
        arrays["viewmats"].append(np.asarray(s.viewmats, np.float64))
        arrays["view_run"].append(np.full(len(rendered), i, np.int64))
        arrays["local"].append(_u8(s.rendered))
        g = r.get("global")
        if g is None:  # no online map captured: an empty (transparent) one
            z = np.zeros(np.shape(s.rendered), np.uint8)
            g = {"grgb": z, "galpha": z[..., 0], "gcrgb": z, "gcalpha": z[..., 0]}
        for k, v in g.items():
            arrays[k].append(v)
        for pre, key in (("obs", "frames"), ("xobs", "xframes")):
            for rgb, depth, vm in r.get(key, []):
                arrays[f"{pre}_rgb"].append(_u8(rgb)[None])
                # millimetres: the local map's depth, exactly enough for re-building it
                arrays[f"{pre}_depth"].append(np.round(np.asarray(depth, np.float64) * 1000).astype(np.uint16)[None])
                arrays[f"{pre}_viewmat"].append(np.asarray(vm, np.float64)[None])
                arrays[f"{pre}_run"].append(np.array([i], np.int64))
        meta_runs["bbox_min"].append(r["bbox"][0])
        meta_runs["bbox_max"].append(r["bbox"][1])
        meta_runs["centroid"].append(np.asarray(r["centroid"], np.float64))
        inst, dist = _nearest_instance(env.house, r["label"], r["centroid"])
        meta_runs["entry"].append(r["entry"])
        meta_runs["instance"].append(inst)
        meta_runs["instance_dist"].append(dist)
        meta_runs["is_goal"].append(inst == ep.goal_instance_id)
        meta_runs["source"].append(r["source"])
        meta_runs["agent_counts_max"].append(int(s.e_max))
    H, W = ep.goal_height, ep.goal_width
    empty = {"rendered": (0, H, W, 3), "alpha": (0, H, W), "holes": (0, H, W), "background": (0, H, W),
             "opencv": (0, H, W, 3), "viewmats": (0, 4, 4), "view_run": (0,), "obs_rgb": (0, H, W, 3),
             "obs_depth": (0, H, W), "obs_viewmat": (0, 4, 4), "obs_run": (0,), "xobs_rgb": (0, H, W, 3),
             "xobs_depth": (0, H, W), "xobs_viewmat": (0, 4, 4), "xobs_run": (0,), "local": (0, H, W, 3),
             "grgb": (0, H, W, 3), "galpha": (0, H, W), "gcrgb": (0, H, W, 3), "gcalpha": (0, H, W)}
    dtypes = {"rendered": np.uint8, "alpha": np.uint8, "holes": bool, "background": bool, "opencv": np.uint8,
              "viewmats": np.float64, "view_run": np.int64, "obs_rgb": np.uint8, "obs_depth": np.uint16,
              "obs_viewmat": np.float64, "obs_run": np.int64, "xobs_rgb": np.uint8, "xobs_depth": np.uint16,
              "xobs_viewmat": np.float64, "xobs_run": np.int64, "local": np.uint8, "grgb": np.uint8,
              "galpha": np.uint8, "gcrgb": np.uint8, "gcalpha": np.uint8}
    out = {k: (np.concatenate(v) if v else np.zeros(empty[k], dtypes[k])) for k, v in arrays.items()}
    out.update({f"run_{k}": np.asarray(v) for k, v in meta_runs.items()})
    out["run_source"] = np.asarray(meta_runs["source"], dtype="<U10")
    for k in ("entry", "instance", "agent_counts_max"):
        out[f"run_{k}"] = np.asarray(meta_runs[k], np.int64)
    out["run_instance_dist"] = np.asarray(meta_runs["instance_dist"], np.float64)
    out["run_is_goal"] = np.asarray(meta_runs["is_goal"], bool)
    for k in ("bbox_min", "bbox_max", "centroid"):
        out[f"run_{k}"] = np.asarray(meta_runs[k], np.float64).reshape(-1, 3)
    out["goal"] = _u8(goal)
    out["K"], out["width"], out["height"] = np.asarray(env.K, np.float64), np.int64(W), np.int64(H)
    out["episode"] = np.asarray(json.dumps(ep.to_json()))
    summary = {"episode_id": ep.episode_id, "house_seed": ep.house_seed, "goal_instance": ep.goal_instance_id,
               "goal_class": ep.goal_class, "success": bool(res.success), "steps": int(res.steps),
               "runs": len(runs), "agent_runs": int(sum(s == "agent" for s in meta_runs["source"])),
               "instances": sorted(set(meta_runs["instance"])), "goal_verified": bool(any(meta_runs["is_goal"])),
               "agent_s": round(t_agent, 1), "max_steps": max_steps,
               "agent_inpainter": type(agent.verifier.inpainter).__name__ if agent is not None else None,
               "agent_nvsm_matcher": type(agent.verifier.nvsm_matcher).__name__ if agent is not None else None}
    out["meta"] = np.asarray(json.dumps(summary))
    buf = io.BytesIO()
    np.savez_compressed(buf, **out)
    atomic_write_bytes(path, buf.getvalue())
    summary["total_s"] = round(time.perf_counter() - t0, 1)
    summary["mb"] = round(len(buf.getvalue()) / 2**20, 2)
    return summary


def episode_path(out: str, ep) -> str:
    return os.path.join(out, f"ep_{ep.house_seed:04d}_{ep.episode_id:03d}.npz")


def load_views(path: str) -> dict:
    """One episode file as a dict of arrays (``episode`` and ``meta`` parsed from JSON)."""
    with np.load(path, allow_pickle=False) as z:
        d = {k: z[k] for k in z.files}
    d["episode"] = json.loads(str(d["episode"]))
    d["meta"] = json.loads(str(d["meta"]))
    return d


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--set", choices=("dev", "eval"), required=True,
                    help="dev: houses --first-house.. (< 1000, for tuning); eval: the evaluation episodes "
                         "(houses 1000+, never tuned on)")
    ap.add_argument("--episodes", type=int, default=8,
                    help="episodes to store, counting only those whose goal has a look-alike (default 8)")
    ap.add_argument("--pool", type=int, default=100,
                    help="episodes sampled to pick them from, in order (default 100, as the issue's eval)")
    ap.add_argument("--first-house", type=int, default=0, help="dev only: first house seed (default 0)")
    ap.add_argument("--seed", type=int, default=0, help="episode sampling seed (default 0, as the eval)")
    ap.add_argument("--max-steps", type=int, default=None,
                    help="step cap per episode (default: the episode's own, 1000)")
    ap.add_argument("--out", required=True, help="output directory (one .npz per episode, resumable)")
    args = ap.parse_args(argv)
    if args.episodes < 1 or args.pool < 1:
        ap.error("--episodes and --pool must be >= 1")
    import warp as wp

    wp.config.quiet = True
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from splatsearch.io import atomic_write_bytes
    from splatsearch.sim.episodes import house_for_episode

    pool = eval_episodes(args.pool, args.seed) if args.set == "eval" else dev_episodes(args.pool, args.first_house,
                                                                                      seed=args.seed)
    chosen, skipped = [], []
    for ep in pool:
        if len(chosen) >= args.episodes:
            break
        (chosen if has_lookalike(house_for_episode(ep), ep) else skipped).append(ep)
    os.makedirs(args.out, exist_ok=True)
    man_path = os.path.join(args.out, "manifest.json")
    manifest = {"set": args.set, "seed": args.seed, "first_house": args.first_house, "max_steps": args.max_steps,
                "episodes": {}, "skipped_no_lookalike": [(e.house_seed, e.episode_id) for e in skipped]}
    if os.path.exists(man_path):
        with open(man_path) as f:
            manifest["episodes"] = json.load(f).get("episodes", {})
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  transient=False) as prog:
        task = prog.add_task(f"NVSM views ({args.set})", total=len(chosen))
        for ep in chosen:
            path = episode_path(args.out, ep)
            if not os.path.exists(path):
                load0 = os.getloadavg()[0]
                s = dump_episode(ep, path, max_steps=args.max_steps)
                s["load1"] = round(load0, 2)
                manifest["episodes"][os.path.basename(path)] = s
                atomic_write_bytes(man_path, json.dumps(manifest, indent=1).encode())
                prog.console.print(json.dumps(s))
            prog.advance(task)
    atomic_write_bytes(man_path, json.dumps(manifest, indent=1).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
