"""Re-render stored NVSM runs with other local-map / crop settings, or with the true geometry (issue 23).

    python benchmarks/nvsm_rerender.py runs/nvsm_views/dev --out runs/nvsm_rr/dev_base
    python benchmarks/nvsm_rerender.py runs/nvsm_views/dev --out runs/nvsm_rr/dev_iters --refine-iters 64
    python benchmarks/nvsm_rerender.py runs/nvsm_views/dev --out runs/nvsm_rr/dev_truth --source truth-region

Reads the episode files of ``benchmarks/nvsm_views.py`` (those written with the runs'
observations, ``obs_*``) and writes files of the same form to ``--out``, so that
``benchmarks/nvsm_separation.py`` scores them unchanged. For every stored run, from the same
cameras (``viewmats``):

- ``--source map`` (default): the object's local map is re-built from the run's stored
  observations (``--frames agent``: those the agent used; ``shadow``: the larger shadow store)
  with ``build_local_map`` and the given :class:`LocalMapConfig` fields, and rendered as
  ``verify_object`` renders it (crop to the region box grown by ``--crop-margin``);
- ``--source truth``: the simulator's ray caster renders the house itself (the ceiling: what a
  perfect map would show, surroundings without limit);
- ``--source truth-region``: the same, with everything outside the crop box (the local map's
  region grown by ``--crop-margin``) filled flat as the NVSM fills cut-away background: what a
  perfect *local* map would show.

The agent is not run again: the cameras, the observations and the episode are the stored ones.
Resumable (an output file that exists is skipped); atomic writes.
"""

from __future__ import annotations

import argparse
import glob
import io
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from nvsm_views import _u8, load_views, split_views  # noqa: E402

SOURCES = ("map", "truth", "truth-region")


def rerender_file(d: dict, *, source: str = "map", margin: float | None = None, crop_margin: float = 0.0,
                  local_map_overrides: dict | None = None, env=None, frames: str = "agent") -> dict:
    """The arrays of one episode file re-rendered (same keys as the input, observations dropped).

    Args:
        d: :func:`load_views` of an episode file that holds ``obs_*`` arrays.
        source: one of :data:`SOURCES`.
        margin: metres of surroundings in the local map's region (default: the agent's
            ``LocalMapConfig.margin``).
        crop_margin: metres the render crop adds around that region (the NVSM's ``crop_margin``).
        local_map_overrides: other :class:`LocalMapConfig` fields (iters_per_frame, refine_iters,
            stride, ...).
        env: a :class:`HouseEnv` of the episode's house (needed for the truth sources).
        frames: "agent" (the observations the agent's local map was built from, ``obs_*``) or
            "shadow" (the shadow store's larger set, ``xobs_*``).
    """
    from splatsearch.agent import AgentConfig
    from splatsearch.mapper import Frame
    from splatsearch.search.inpainting import OpenCVInpainter, holes_from_alpha
    from splatsearch.search.local_map import LocalMapConfig, build_local_map, region_box
    from splatsearch.search.novel_views import crop_box_for, render_novel_views

    pre = {"agent": "obs", "shadow": "xobs"}.get(frames)
    if pre is None:
        raise ValueError(f"frames must be 'agent' or 'shadow', got {frames!r}")
    if f"{pre}_run" not in d:
        raise ValueError(f"this episode file has no {pre}_* observations (dump it again with nvsm_views.py)")
    if source not in SOURCES:
        raise ValueError(f"source must be one of {SOURCES}, got {source!r}")
    agent = AgentConfig(variant="splatsearch", colour_cue=False)
    base = agent.local_map
    fields = {k: getattr(base, k) for k in base.__dataclass_fields__}
    fields.update(local_map_overrides or {})
    if margin is not None:
        fields["margin"] = float(margin)
    lm_cfg = LocalMapConfig(**fields)
    K = np.asarray(d["K"], np.float64)
    W, H = int(d["width"]), int(d["height"])
    alpha_tau, fill = float(agent.inpaint_tau), 0.5
    inp = OpenCVInpainter()
    out = {k: [] for k in ("rendered", "alpha", "holes", "background", "opencv", "viewmats", "view_run")}
    build_wall, build_cpu = [], []
    for r in range(len(d["run_entry"])):
        lo, hi = region_box(d["run_bbox_min"][r], d["run_bbox_max"][r], lm_cfg.margin)
        box = crop_box_for(lo, hi, crop_margin, floor_z=None)
        vms = d["viewmats"][d["view_run"] == r]
        if source == "map":
            sel = d[f"{pre}_run"] == r
            obs = [Frame(rgb.astype(np.float32) / 255.0, dep.astype(np.float32) / 1000.0, vm.astype(np.float32))
                   for rgb, dep, vm in zip(d[f"{pre}_rgb"][sel], d[f"{pre}_depth"][sel], d[f"{pre}_viewmat"][sel])]
            t0, c0 = time.perf_counter(), time.process_time()
            gmap = build_local_map(obs, K, W, H, lo, hi, lm_cfg, seed=agent.seed)
            build_wall.append(time.perf_counter() - t0)
            build_cpu.append(time.process_time() - c0)
            rgb, alpha = render_novel_views(gmap, vms, K, W, H, crop_box=box)
            rgb, alpha = np.asarray(rgb, np.float32), np.asarray(alpha, np.float32)
        else:
            rgb, alpha = [], []
            for vm in vms:
                f = env.renderer.render(vm, K, W, H, max_depth=env.max_depth)
                a = (f.depth > 0).astype(np.float32)
                if source == "truth-region":
                    a = a * _inside_box(f.depth, vm, K, box)
                rgb.append(np.asarray(f.rgb, np.float32))
                alpha.append(a)
            rgb, alpha = np.stack(rgb), np.stack(alpha)
        holes = holes_from_alpha(alpha, alpha_tau)
        rendered, interior, background = split_views(rgb, holes, alpha, alpha_tau, fill)
        out["rendered"].append(_u8(rendered))
        out["alpha"].append(_u8(alpha))
        out["holes"].append(interior)
        out["background"].append(background)
        out["opencv"].append(_u8(inp.inpaint(rendered, interior)))
        out["viewmats"].append(vms)
        out["view_run"].append(np.full(len(vms), r, np.int64))
    res = {k: np.concatenate(v) for k, v in out.items()}
    for k, v in d.items():
        if k.startswith("run_") or k in ("goal", "K", "width", "height"):
            res[k] = v
    if build_wall:
        # wall seconds depend on the machine's load; process CPU seconds less so
        res["run_build_s"] = np.asarray(build_wall, np.float64)
        res["run_build_cpu_s"] = np.asarray(build_cpu, np.float64)
    res["episode"] = np.asarray(json.dumps(d["episode"]))
    meta = dict(d["meta"])
    meta["rerender"] = {"source": source, "frames": frames, "crop_margin": crop_margin, "local_map": {k: getattr(lm_cfg, k) for k in fields}}
    res["meta"] = np.asarray(json.dumps(meta))
    return res


def _inside_box(depth: np.ndarray, viewmat: np.ndarray, K: np.ndarray, box) -> np.ndarray:
    """(H, W) float 1 where the pixel's surface point (from its depth) lies in ``box``, else 0."""
    H, W = depth.shape
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    z = depth.astype(np.float64)
    pc = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z, np.ones_like(z)], -1)
    pw = pc @ np.linalg.inv(np.asarray(viewmat, np.float64)).T
    lo, hi = box
    ok = np.all((pw[..., :3] >= np.asarray(lo) - 1e-6) & (pw[..., :3] <= np.asarray(hi) + 1e-6), -1) & (z > 0)
    return ok.astype(np.float32)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("views", help="directory of episode .npz files from benchmarks/nvsm_views.py (with obs_* arrays)")
    ap.add_argument("--out", required=True, help="output directory (same file form; resumable)")
    ap.add_argument("--source", choices=SOURCES, default="map",
                    help="map: re-build the local map and render it; truth: the simulator's ray caster; "
                         "truth-region: the ray caster with everything outside the crop box filled flat")
    ap.add_argument("--frames", choices=("agent", "shadow"), default="agent",
                    help="map source only: the agent's stored observations (obs_*, default) or the shadow store's "
                         "larger set (xobs_*, more keyframes)")
    ap.add_argument("--margin", type=float, default=None,
                    help="metres of surroundings in the local map's region (default: LocalMapConfig.margin)")
    ap.add_argument("--crop-margin", type=float, default=0.0,
                    help="metres the render crop adds around that region (the NVSM's crop_margin; default 0)")
    ap.add_argument("--iters-per-frame", type=int, default=None, help="LocalMapConfig.iters_per_frame override")
    ap.add_argument("--refine-iters", type=int, default=None, help="LocalMapConfig.refine_iters override")
    ap.add_argument("--stride", type=int, default=None, help="LocalMapConfig.stride override (densify stride, px)")
    args = ap.parse_args(argv)
    if args.margin is not None and not args.margin >= 0:
        ap.error("--margin must be >= 0")
    if not args.crop_margin >= 0:
        ap.error("--crop-margin must be >= 0")
    for k in ("iters_per_frame", "refine_iters"):
        if getattr(args, k) is not None and getattr(args, k) < 0:
            ap.error(f"--{k.replace('_', '-')} must be >= 0")
    if args.stride is not None and args.stride < 1:
        ap.error("--stride must be >= 1")
    files = sorted(glob.glob(os.path.join(args.views, "ep_*.npz")))
    if not files:
        ap.error(f"no ep_*.npz files in {args.views!r}")
    import warp as wp

    wp.config.quiet = True
    from splatsearch.io import atomic_write_bytes
    from splatsearch.sim.env import HouseEnv
    from splatsearch.sim.episodes import Episode, house_for_episode

    overrides = {k: getattr(args, k) for k in ("iters_per_frame", "refine_iters", "stride") if getattr(args, k) is not None}
    os.makedirs(args.out, exist_ok=True)
    for f in files:
        path = os.path.join(args.out, os.path.basename(f))
        if os.path.exists(path):
            continue
        t0 = time.perf_counter()
        d = load_views(f)
        env = None
        if args.source != "map":
            ep = Episode.from_json(d["episode"])
            env = HouseEnv(house_for_episode(ep), width=int(d["width"]), height=int(d["height"]))
        res = rerender_file(d, source=args.source, margin=args.margin, crop_margin=args.crop_margin,
                            local_map_overrides=overrides, env=env, frames=args.frames)
        buf = io.BytesIO()
        np.savez_compressed(buf, **res)
        atomic_write_bytes(path, buf.getvalue())
        rec = {"file": os.path.basename(f), "runs": int(len(d["run_entry"])),
               "s": round(time.perf_counter() - t0, 1), "load1": round(os.getloadavg()[0], 2)}
        if "run_build_s" in res:
            rec["build_s"] = round(float(res["run_build_s"].sum()), 1)
            rec["build_cpu_s"] = round(float(res["run_build_cpu_s"].sum()), 1)
        print(json.dumps(rec), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
