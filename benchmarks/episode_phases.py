"""Where a search episode's time goes: wall and CPU seconds per phase (issue 23's wall-time target).

    python benchmarks/episode_phases.py --first-house 504 --only 7,8 --out /tmp/phases
    python benchmarks/episode_phases.py --summary /tmp/phases

Runs dev episodes exactly as ``benchmarks/look_again_dev.py`` does (same selection, same agent
settings; its per-episode JSON plus a ``phases`` table), with timers wrapped around the functions
below. A phase's time is *exclusive*: time spent in a nested timed phase counts for that phase
only (e.g. the NVSM's local map is not also in ``nvsm_other``). CPU time is the process's (all
threads: JAX, Warp, OpenCV). ``jit_compile_s`` is the wall time JAX reports for tracing, lowering
and compiling (``jax.monitoring``), which overlaps the phase that triggered it. ``other`` is the
episode's wall time minus every timed phase (the agent's own bookkeeping, lifting by depth, the
observation store, ...). The timers add a few microseconds per call and change no decision.

Dev houses only (seeds below 1000); one process runs its episodes in turn after the warm-up that
``splatsearch eval --workers 1`` does (threads, the persistent JAX compile cache, Warp kernels), so
compiles are paid in the first one or loaded from the cache, as there.
"""

from __future__ import annotations

import argparse
import glob
import importlib
import json
import os
import sys
import time
from collections import defaultdict

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

#: (phase, module, attribute path): the function wrapped where the caller looks it up
PHASES = [
    ("sim_setup", "splatsearch.sim.env", "HouseEnv.__init__"),
    ("sim_step", "splatsearch.sim.env", "HouseEnv.step"),
    ("sim_step", "splatsearch.sim.env", "HouseEnv.reset"),
    ("agent_init", "splatsearch.agent.core", "SplatSearchAgent.__init__"),
    ("nav_observe", "splatsearch.nav.exploration", "ExplorationPlanner.observe"),
    ("map_online", "splatsearch.agent.perception", "Perception.map_frame"),
    ("detect", "splatsearch.agent.perception", "Perception.detect"),
    ("lift_ids", "splatsearch.agent.perception", "map_top_ids"),
    ("lift_ids", "splatsearch.agent.perception", "lift_mask_ids"),
    ("lift_depth", "splatsearch.agent.perception", "lift_mask_depth"),
    ("obs_store", "splatsearch.search.local_map", "ObservationStore.add"),
    ("crop_match", "splatsearch.agent.verification", "Verifier.match_observation"),
    ("nvsm_other", "splatsearch.agent.verification", "Verifier.verify"),
    ("nvsm_viewpoints", "splatsearch.agent.verification", "Verifier.nvsm_viewpoints"),
    ("nvsm_local_map", "splatsearch.agent.verification", "build_local_map"),
    ("nvsm_render", "splatsearch.search.object_search", "render_novel_views"),
    ("nvsm_complete", "splatsearch.search.completion", "VCICNInpainter.inpaint"),
    ("nvsm_complete", "splatsearch.search.inpainting", "OpenCVInpainter.inpaint"),
    ("nvsm_match", "splatsearch.search.object_search", "best_view"),
    ("plan_explore", "splatsearch.nav.exploration", "ExplorationPlanner.act"),
    ("plan_look_again", "splatsearch.agent.decision", "choose_viewpoint"),
    ("decide_other", "splatsearch.agent.decision", "SearchPolicy.decide"),
]


class PhaseTimer:
    """Exclusive wall / process-CPU seconds and call counts per phase name."""

    def __init__(self):
        self.wall: dict[str, float] = defaultdict(float)
        self.cpu: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)
        self._stack: list[list[float]] = []  # per open call: [children's wall, children's cpu]
        self.compile_s = 0.0
        self.compiles: dict[str, int] = defaultdict(int)

    def wrap(self, name: str, fn):
        def timed(*args, **kwargs):
            t0, c0 = time.perf_counter(), time.process_time()
            self._stack.append([0.0, 0.0])
            try:
                return fn(*args, **kwargs)
            finally:
                dw, dc = time.perf_counter() - t0, time.process_time() - c0
                cw, cc = self._stack.pop()
                self.wall[name] += dw - cw
                self.cpu[name] += dc - cc
                self.calls[name] += 1
                if self._stack:
                    self._stack[-1][0] += dw
                    self._stack[-1][1] += dc

        timed.__wrapped__ = fn
        return timed

    def on_jax_event(self, event: str, duration: float, **kwargs) -> None:
        if event.startswith("/jax/core/compile/"):
            self.compile_s += duration
            if event.endswith("backend_compile_duration"):
                self.compiles[str(kwargs.get("fun_name", "?"))] += 1

    def install(self) -> None:
        for name, mod, path in PHASES:
            owner = importlib.import_module(mod)
            *outer, attr = path.split(".")
            for part in outer:
                owner = getattr(owner, part)
            setattr(owner, attr, self.wrap(name, getattr(owner, attr)))
        import jax

        jax.monitoring.register_event_duration_secs_listener(self.on_jax_event)

    def snapshot(self) -> dict:
        return {"wall": dict(self.wall), "cpu": dict(self.cpu), "calls": dict(self.calls),
                "compile_s": self.compile_s, "compiles": dict(self.compiles)}


def diff(after: dict, before: dict) -> dict:
    """Per-episode phase table from two snapshots of one :class:`PhaseTimer`."""
    out = {}
    for k in after["wall"]:
        out[k] = {"wall_s": round(after["wall"][k] - before["wall"].get(k, 0.0), 3),
                  "cpu_s": round(after["cpu"][k] - before["cpu"].get(k, 0.0), 3),
                  "calls": after["calls"][k] - before["calls"].get(k, 0)}
    return out


def summary(dirs: list[str]) -> int:
    """Print each folder's phase table: per phase the wall and CPU seconds summed over its
    episodes and the share of the episodes' wall time."""
    for d in dirs:
        rows = [json.load(open(p)) for p in sorted(glob.glob(os.path.join(d, "ep_*.json")))]
        if not rows:
            continue
        tot_w = sum(r["wall_s"] for r in rows)
        tot_c = sum(r.get("cpu_s", 0.0) for r in rows)
        agg: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0, 0])
        for r in rows:
            for k, v in r["phases"].items():
                a = agg[k]
                a[0] += v["wall_s"]
                a[1] += v["cpu_s"]
                a[2] += v["calls"]
        timed_w = sum(a[0] for a in agg.values())
        timed_c = sum(a[1] for a in agg.values())
        agg["other"] = [tot_w - timed_w, tot_c - timed_c, 0]
        print(f"{d}: {len(rows)} episodes, {sum(r['steps'] for r in rows)} steps, "
              f"{sum(r['nvsm_runs'] for r in rows)} NVSM runs, wall {tot_w:.1f} s, CPU {tot_c:.1f} s, "
              f"JAX compile {sum(r['jit_compile_s'] for r in rows):.1f} s wall")
        print(f"  {'phase':<16} {'wall s':>8} {'share':>6} {'cpu s':>8} {'calls':>6}")
        for k, (w, c, n) in sorted(agg.items(), key=lambda kv: -kv[1][0]):
            print(f"  {k:<16} {w:8.1f} {w / max(tot_w, 1e-9):6.1%} {c:8.1f} {int(n):6d}")
        for r in rows:
            print(f"  {r['house_seed']}/{r['episode_id']}: {'S' if r['success'] else 'F'} {r['steps']} steps, "
                  f"{r['nvsm_runs']} NVSM, wall {r['wall_s']} s, cpu {r.get('cpu_s')} s, "
                  f"compile {r['jit_compile_s']:.1f} s, load {r['load1_start']}")
    return 0


def compare(a_dir: str, b_dir: str) -> int:
    """Whether the episodes two runs share decided the same: success, steps, path length, NVSM runs,
    every entry's e_max and the look-again / confirm trips must be equal (e_max to 1e-6); prints
    the CPU and wall seconds of each episode and the median speed-up. Returns 1 if any differ."""
    a = {os.path.basename(p): json.load(open(p)) for p in glob.glob(os.path.join(a_dir, "ep_*.json"))}
    b = {os.path.basename(p): json.load(open(p)) for p in glob.glob(os.path.join(b_dir, "ep_*.json"))}
    common = sorted(set(a) & set(b))
    bad, ratios_c, ratios_w = 0, [], []
    for k in common:
        x, y = a[k], b[k]
        same = (x["success"] == y["success"] and x["steps"] == y["steps"]
                and abs(x["path_length"] - y["path_length"]) < 1e-9 and x["nvsm_runs"] == y["nvsm_runs"]
                and len(x["entries"]) == len(y["entries"])
                and all(abs(p["e_max"] - q["e_max"]) < 1e-6 for p, q in zip(x["entries"], y["entries"]))
                and [(t["kind"], t["outcome"], t["start"], t["end"]) for t in x["look_log"]]
                == [(t["kind"], t["outcome"], t["start"], t["end"]) for t in y["look_log"]])
        bad += not same
        cx, cy = x.get("cpu_s"), y.get("cpu_s")
        if cx and cy:
            ratios_c.append(cx / cy)
        ratios_w.append(x["wall_s"] / y["wall_s"])
        print(f"{k}: {'same' if same else 'DIFFERENT'}: {'S' if x['success'] else 'F'} {x['steps']} steps "
              f"{x['path_length']:.2f} m vs {'S' if y['success'] else 'F'} {y['steps']} steps {y['path_length']:.2f} m; "
              f"cpu {cx} -> {cy} s, wall {x['wall_s']} -> {y['wall_s']} s (load {x['load1_start']} / {y['load1_start']})")
    if common:
        print(f"{len(common)} episodes, {bad} different; median speed-up CPU {np.median(ratios_c) if ratios_c else float('nan'):.3f}x, "
              f"wall {np.median(ratios_w):.3f}x; total CPU {sum(a[k].get('cpu_s', 0) for k in common):.1f} -> "
              f"{sum(b[k].get('cpu_s', 0) for k in common):.1f} s")
    return int(bad > 0)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--episodes", type=int, default=16, help="dev episodes with a look-alike (default 16)")
    ap.add_argument("--first-house", type=int, default=500, help="first dev house seed (default 500, < 1000)")
    ap.add_argument("--only", default=None, help="comma-separated episode indices (0-based) of the selection")
    ap.add_argument("--max-steps", type=int, default=None, help="step cap (default the episode's)")
    ap.add_argument("--look-again", type=int, default=1, help="AgentConfig.look_again (default 1, today's default)")
    ap.add_argument("--agent", action="append", default=[], metavar="FIELD=VALUE",
                    help="extra AgentConfig field (dotted for a nested one: local_map.refine_iters=8)")
    ap.add_argument("--out", default=None, help="output folder (one JSON per episode)")
    ap.add_argument("--compare", nargs=2, default=None, metavar=("BEFORE", "AFTER"),
                    help="check that two runs' shared episodes decided the same, print the speed-up and exit")
    ap.add_argument("--summary", nargs="+", default=None, metavar="DIR", help="print finished runs' tables and exit")
    args = ap.parse_args(argv)
    if args.summary:
        return summary(args.summary)
    if args.compare:
        return compare(*args.compare)
    if args.out is None:
        ap.error("--out is needed to run")
    from splatsearch.kernels.parallel import cpu_threads
    from splatsearch.parallel import warm_worker

    # the warm-up `splatsearch eval --workers 1` does: threads, the persistent JAX compile cache,
    # Warp's kernels loaded
    warm_worker(cpu_threads(), ("splatsearch.episode",))
    from look_again_dev import parse_agent_overrides, run
    from nvsm_views import dev_episodes, has_lookalike

    from splatsearch.evaluation import EVAL_SEED_BASE
    from splatsearch.io import atomic_write_bytes
    from splatsearch.sim.episodes import house_for_episode

    if args.first_house + 10 >= EVAL_SEED_BASE:
        ap.error("dev houses only (seeds below 1000)")
    overrides = parse_agent_overrides(args.agent)
    pool = dev_episodes(100, args.first_house, seed=0)
    chosen = [ep for ep in pool if has_lookalike(house_for_episode(ep), ep)][:args.episodes]
    if args.only:
        chosen = [chosen[int(i)] for i in args.only.split(",")]
    timer = PhaseTimer()
    timer.install()
    os.makedirs(args.out, exist_ok=True)
    for ep in chosen:
        before = timer.snapshot()
        r = run(ep, args.look_again, args.max_steps, overrides)
        after = timer.snapshot()
        r["phases"] = diff(after, before)
        r["jit_compile_s"] = round(after["compile_s"] - before["compile_s"], 3)
        r["jit_compiles"] = {k: v - before["compiles"].get(k, 0) for k, v in after["compiles"].items()
                             if v - before["compiles"].get(k, 0)}
        name = f"ep_{ep.house_seed:04d}_{ep.episode_id:03d}.json"
        atomic_write_bytes(os.path.join(args.out, name), json.dumps(r, indent=1).encode())
        print(json.dumps({k: r[k] for k in ("house_seed", "episode_id", "success", "steps", "wall_s", "cpu_s",
                                             "jit_compile_s")}), flush=True)
    return summary([args.out])


if __name__ == "__main__":
    sys.exit(main())
