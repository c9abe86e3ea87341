"""SR / SPL of the look-again step on dev look-alike houses (issue 23; never evaluation houses).

    python benchmarks/look_again_dev.py --look-again 0 --out runs/look_again/la0
    python benchmarks/look_again_dev.py --look-again 1 --out runs/look_again/la1
    python benchmarks/look_again_dev.py --summary runs/look_again/la0 runs/look_again/la1

The episodes are those of ``benchmarks/nvsm_views.py --set dev --first-house 500 --episodes 16``
(val-hard episodes of look-alike houses 500 onward whose goal has a same-class instance, sampled
as the evaluation samples its own), run with the ``splatsearch`` variant identifying by feature
matches alone (``colour_cue=False``, as ``splatsearch eval --identical-furniture
--no-appearance``). One ``OUT/ep_<house>_<id>.json`` per episode (atomic, resumable) with the
outcome, the look-again trips (``SearchPolicy.look_log``), and every object entry's final e_max with
the simulator instance it maps to, so that the goal's count can be compared with the best
look-alike's (the agent's own verification counts, camera-image scale).
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def parse_agent_overrides(pairs: list[str]) -> dict:
    """`--agent FIELD=VALUE` pairs -> {field: int | float | str} (a text value stays a string)."""
    overrides = {}
    for kv in pairs:
        k, v = kv.split("=", 1)
        try:
            overrides[k] = int(v) if v.lstrip("-").isdigit() else float(v)
        except ValueError:
            overrides[k] = v  # a text field, e.g. confirm_by=rivals
    return overrides


def agent_config(look_again: int, overrides: dict, colour: bool = False):
    """The episode's :class:`AgentConfig`: variant ``splatsearch`` with ``overrides``; a dotted key
    (``local_map.refine_iters``) sets a field of a nested config (as ``--agent.local_map.*``)."""
    from splatsearch.agent import AgentConfig
    from splatsearch.cli_config import apply_overrides

    flat = {k: v for k, v in overrides.items() if "." not in k}
    nested: dict = {}
    for k, v in overrides.items():
        if "." in k:
            *path, leaf = k.split(".")
            node = nested
            for p in path:
                node = node.setdefault(p, {})
            node[leaf] = v
    cfg = AgentConfig(variant="splatsearch", colour_cue=colour, look_again=look_again, **flat)
    return apply_overrides(cfg, nested) if nested else cfg


def run(ep, look_again: int, max_steps: int | None, overrides: dict, colour: bool = False) -> dict:
    from nvsm_views import _nearest_instance

    from splatsearch.agent import AgentConfig
    from splatsearch.episode import run_episode
    from splatsearch.sim.env import HouseEnv
    from splatsearch.sim.episodes import house_for_episode

    env = HouseEnv(house_for_episode(ep), width=ep.goal_width, height=ep.goal_height)
    cfg = agent_config(look_again, overrides, colour)
    holder = {}
    statuses = []

    ambiguous = [0]

    def on_step(agent, _obs, info):
        holder["agent"] = agent
        statuses.append(info.status)
        # a step at which look_again >= 1 would have begun (or kept) a trip: nothing taken for the
        # goal and an ambiguous entry left (for look_again 0 this tells whether 1 could differ)
        if not agent.goal_candidates() and any(agent.verifier.is_ambiguous(e) and e.id not in agent.policy.given_up
                                               for e in agent.db):
            ambiguous[0] += 1

    t0 = time.perf_counter()
    c0 = time.process_time()  # this process's CPU seconds (all threads): steadier than wall on a shared machine
    load0 = os.getloadavg()[0]
    r = run_episode(ep, cfg, env=env, max_steps=max_steps, on_step=on_step)
    agent = holder["agent"]
    entries = []
    for e in agent.db:
        inst, dist = _nearest_instance(env.house, e.label, e.centroid)
        entries.append({"entry": e.id, "instance": inst, "dist": round(dist, 2), "is_goal": inst == ep.goal_instance_id,
                        "e_max": e.e_max, "n_nvsm": e.n_nvsm, "matched": e.matched,
                        # every non-zero count with its step and kind: which frame made or broke a match
                        "counts": getattr(agent.verifier, "count_log", {}).get(e.id, [])})
    out = r.to_json()
    out.pop("trajectory")
    out.update({"look_again": look_again, "look_log": agent.policy.look_log, "entries": entries,
                "refuted": {str(k): v for k, v in agent.policy.refuted.items()},
                "confirmed": sorted(agent.policy.confirmed),
                "ambiguous_steps": ambiguous[0],
                "look_again_steps": statuses.count("look_again"), "load1_start": round(load0, 2),
                "load1_end": round(os.getloadavg()[0], 2), "wall_s": round(time.perf_counter() - t0, 1),
                "cpu_s": round(time.process_time() - c0, 1),
                "overrides": overrides})
    return out


def default_episodes(n: int, first_house: int, per_house: int = 5) -> list:
    """``n`` val-hard episodes in default (not look-alike) houses ``first_house, ...`` (< 1000),
    sampled as :func:`nvsm_views.dev_episodes` samples the look-alike ones."""
    from splatsearch import sim
    from splatsearch.evaluation import EVAL_SEED_BASE

    eps, hs = [], first_house
    while len(eps) < n:
        if hs >= EVAL_SEED_BASE:
            raise ValueError(f"dev houses must stay below {EVAL_SEED_BASE}")
        house = sim.make_house(hs)
        for e in sim.make_episodes(house, min(per_house, n - len(eps)), "val-hard", seed=0, env=sim.HouseEnv(house)):
            e.episode_id = len(eps)
            eps.append(e)
        hs += 1
    return eps


def separation(rows: list[dict]) -> dict:
    """Per episode the goal instance's best e_max vs the best look-alike's (over entries that map to
    an instance within 1 m); ROC AUC over all goal vs look-alike objects, and paired W/T/L."""
    goals, others, wtl = [], [], [0, 0, 0]
    for r in rows:
        best: dict[int, float] = {}
        for e in r["entries"]:
            if e["dist"] <= 1.0 and e["e_max"] >= 0:
                best[e["instance"]] = max(best.get(e["instance"], 0.0), e["e_max"])
        g = [v for k, v in best.items() if any(x["is_goal"] for x in r["entries"] if x["instance"] == k)]
        o = [v for k, v in best.items() if not any(x["is_goal"] for x in r["entries"] if x["instance"] == k)]
        goals += g
        others += o
        if g and o:
            d = max(g) - max(o)
            wtl[0 if d > 0 else (1 if d == 0 else 2)] += 1
    if goals and others:
        gg, oo = np.asarray(goals)[:, None], np.asarray(others)[None, :]
        auc = float(((gg > oo) + 0.5 * (gg == oo)).mean())
    else:
        auc = float("nan")
    return {"auc": auc, "n_goals": len(goals), "n_lookalikes": len(others), "wtl": wtl}


def summary(dirs: list[str]) -> int:
    per = {}
    for d in dirs:
        rows = [json.load(open(p)) for p in sorted(glob.glob(os.path.join(d, "ep_*.json")))]
        per[d] = {(r["house_seed"], r["episode_id"]): r for r in rows}
    common = sorted(set.intersection(*(set(v) for v in per.values()))) if per else []
    print(f"{len(common)} episodes finished in every run")
    for d, rows in per.items():
        rs = [rows[k] for k in common]
        n = max(len(rs), 1)
        sr = sum(r["success"] for r in rs) / n
        spl = sum(r["spl"] for r in rs) / n
        trips = sum(len([x for x in r["look_log"] if x["outcome"] != "no_viewpoint"]) for r in rs)
        cap = sum(sum(x["outcome"] in ("captured", "confirmed", "refuted") for x in r["look_log"]) for r in rs)
        la_steps = sum(r["look_again_steps"] for r in rs)
        sep = separation(rs)
        print(f"{d}: SR {sr:.3f} ({sum(r['success'] for r in rs)}/{len(rs)}), SPL {spl:.3f}, "
              f"median steps {np.median([r['steps'] for r in rs]) if rs else 0:.0f}, "
              f"median wall {np.median([r['wall_s'] for r in rs]) if rs else 0:.0f} s, trips {trips} "
              f"(captured {cap}), look-again steps {la_steps}; agent e_max separation AUC {sep['auc']:.3f} "
              f"({sep['n_goals']} goals, {sep['n_lookalikes']} look-alikes), W/T/L {sep['wtl']}")
    if len(per) == 2 and common:
        a, b = (per[d] for d in dirs)
        w = sum(b[k]["success"] and not a[k]["success"] for k in common)
        l_ = sum(a[k]["success"] and not b[k]["success"] for k in common)
        print(f"paired successes, {dirs[1]} vs {dirs[0]}: {w} won, {l_} lost, {len(common) - w - l_} tied")
        for k in common:
            if a[k]["success"] != b[k]["success"] or a[k]["steps"] != b[k]["steps"]:
                print(f"  {k}: {a[k]['success']}/{a[k]['steps']} steps -> {b[k]['success']}/{b[k]['steps']} steps; "
                      f"trips {[(x['outcome'], x['e_max_before'], x['e_max_after']) for x in b[k]['look_log']]}")
    return 0


def trips(dirs: list[str], tau_m: float = 15.0) -> int:
    """Print every confirm trip of the runs in ``dirs``: whether its entry is the goal, the count
    that made the match (the first >= tau_m in the entry's count log: step, kind), the best count
    before the trip, the confirming frame's own count, the outcome, and where it looked from (the
    azimuth gap to the stored observations, the viewpoint's and the stored cameras' distances)."""
    for d in dirs:
        for p in sorted(glob.glob(os.path.join(d, "ep_*.json"))):
            r = json.load(open(p))
            ent = {e["entry"]: e for e in r["entries"]}
            for x in r["look_log"]:
                if x["kind"] != "confirm":
                    continue
                e = ent.get(x["entry"], {})
                first = next((c for c in e.get("counts", []) if c[2] >= tau_m), None)
                g = x.get("geometry") or {}
                seen = g.get("seen_dist_m") or []
                print(f"{r['house_seed']}/{r['episode_id']} {'S' if r['success'] else 'F'} {r['steps']} steps: "
                      f"entry {x['entry']} {'GOAL' if e.get('is_goal') else 'look-alike'}, match made by "
                      f"{first}, e_max {x['e_max_before']:.0f} -> new frame {x['count_new']} "
                      f"({x['outcome']}, steps {x['start']}-{x['end']}); gap {g.get('gap_deg')} deg, viewpoint "
                      f"{g.get('view_dist_m')} m, stored cameras {len(seen)} at median "
                      f"{np.median(seen) if seen else float('nan'):.2f} m, e_max camera az {g.get('best_az_deg')}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--look-again", type=int, default=0, help="AgentConfig.look_again (views per ambiguous object)")
    ap.add_argument("--episodes", type=int, default=16, help="dev episodes with a look-alike (default 16)")
    ap.add_argument("--first-house", type=int, default=500, help="first dev house seed (default 500, < 1000)")
    ap.add_argument("--max-steps", type=int, default=None, help="step cap (default the episode's, 1000)")
    ap.add_argument("--only", default=None, help="comma-separated episode indices (0-based) of the 16 to run")
    ap.add_argument("--agent", action="append", default=[], metavar="FIELD=VALUE",
                    help="extra AgentConfig field (int, float or text), e.g. look_again_low=8; a dotted name sets a "
                         "nested config's field, e.g. local_map.refine_iters=8")
    ap.add_argument("--out", default=None, help="output folder (one JSON per episode, resumable)")
    ap.add_argument("--reverse", action="store_true", help="run the episodes last first")
    ap.add_argument("--pair", default=None, metavar="DIR",
                    help="the output folder of the other setting (look_again 0 vs >= 1): an episode in which "
                         "the look-again run began no trip, or the look_again-0 run never had an ambiguous entry "
                         "while nothing was the goal, is the same in both (deterministic), so its result is "
                         "copied (marked deduced_from) instead of run")
    ap.add_argument("--copy-unmatched", default=None, metavar="DIR",
                    help="a look_again-0 run without confirm: an episode in which no entry of it ever reached "
                         "tau_m is the same under confirm_below with look_again 0 or look_again_after_refute "
                         "(no confirm trip, so no refutation and no look-again trip), so its result is copied "
                         "(marked deduced_from) instead of run")
    ap.add_argument("--copy-unrefuted", default=None, metavar="DIR",
                    help="a run with refute_radius 0: an episode in which it refuted no match is the same with "
                         "any refute_radius (a refusal that never happened covers no duplicate), so its result is "
                         "copied (marked deduced_from) instead of run")
    ap.add_argument("--colour", action="store_true",
                    help="default houses (no look-alike furniture) with the colour cue on, as `splatsearch eval` "
                         "without --identical-furniture: a check that the look-again/confirm settings keep that SR")
    ap.add_argument("--summary", nargs="+", default=None, metavar="DIR", help="summarise finished runs and exit")
    ap.add_argument("--trips", nargs="+", default=None, metavar="DIR",
                    help="list every confirm trip of finished runs (goal or look-alike, counts, viewpoint gap) and exit")
    args = ap.parse_args(argv)
    if args.summary:
        return summary(args.summary)
    if args.trips:
        return trips(args.trips)
    if args.out is None:
        ap.error("--out is needed to run")
    import warp as wp

    wp.config.quiet = True
    from nvsm_views import dev_episodes, has_lookalike

    from splatsearch.evaluation import EVAL_SEED_BASE
    from splatsearch.io import atomic_write_bytes
    from splatsearch.search.matching import DEFAULT_TAU_M
    from splatsearch.sim.episodes import house_for_episode

    if args.first_house + 10 >= EVAL_SEED_BASE:
        ap.error("dev houses only (seeds below 1000)")
    overrides = parse_agent_overrides(args.agent)
    pool = dev_episodes(100, args.first_house, seed=0) if not args.colour else default_episodes(100, args.first_house)
    chosen = [ep for ep in pool if has_lookalike(house_for_episode(ep), ep)][:args.episodes]
    if args.only:
        chosen = [chosen[int(i)] for i in args.only.split(",")]
    os.makedirs(args.out, exist_ok=True)
    if args.reverse:
        chosen = chosen[::-1]
    for ep in chosen:
        name = f"ep_{ep.house_seed:04d}_{ep.episode_id:03d}.json"
        path = os.path.join(args.out, name)
        if os.path.exists(path):
            continue
        if args.copy_unmatched:
            src = os.path.join(args.copy_unmatched, name)
            o = json.load(open(src)) if os.path.exists(src) else None
            if args.look_again > 0 and not overrides.get("look_again_after_refute"):
                ap.error("--copy-unmatched needs --look-again 0 or --agent look_again_after_refute=1")
            if o is not None and o["look_again"] == 0 and not o["overrides"].get("confirm_below") and all(
                    e["e_max"] < o["overrides"].get("tau_m", DEFAULT_TAU_M) for e in o["entries"]):
                o.update({"look_again": args.look_again, "look_log": [], "look_again_steps": 0, "refuted": {},
                          "confirmed": [], "overrides": overrides, "deduced_from": args.copy_unmatched})
                atomic_write_bytes(path, json.dumps(o, indent=1).encode())
                print(json.dumps({"deduced": name, "from": args.copy_unmatched}), flush=True)
                continue
        if args.copy_unrefuted:
            src = os.path.join(args.copy_unrefuted, name)
            o = json.load(open(src)) if os.path.exists(src) else None
            if o is not None and not o["overrides"].get("refute_radius") and not o["refuted"]:
                o.update({"overrides": overrides, "deduced_from": args.copy_unrefuted})
                atomic_write_bytes(path, json.dumps(o, indent=1).encode())
                print(json.dumps({"deduced": name, "from": args.copy_unrefuted}), flush=True)
                continue
        other = os.path.join(args.pair, name) if args.pair else None
        if other and os.path.exists(other):
            o = json.load(open(other))
            began = [x for x in o["look_log"] if x["outcome"] != "no_viewpoint"]
            same = (o["look_again"] >= 1 and not began) if args.look_again == 0 else (
                o["look_again"] == 0 and o.get("ambiguous_steps", 1) == 0)
            if same:
                o.update({"look_again": args.look_again, "look_log": [], "look_again_steps": 0,
                          "deduced_from": args.pair})
                atomic_write_bytes(path, json.dumps(o, indent=1).encode())
                print(json.dumps({"deduced": name, "from": args.pair}), flush=True)
                continue
        r = run(ep, args.look_again, args.max_steps, overrides, colour=args.colour)
        atomic_write_bytes(path, json.dumps(r, indent=1).encode())
        if other and not os.path.exists(other) and args.look_again == 0 and r["ambiguous_steps"] == 0:
            o = dict(r, look_again=1, deduced_from=args.out)  # the look-again run would be the same
            atomic_write_bytes(other, json.dumps(o, indent=1).encode())
        print(json.dumps({k: r[k] for k in ("house_seed", "episode_id", "success", "spl", "steps", "wall_s", "cpu_s",
                                             "look_again_steps", "load1_start")}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
