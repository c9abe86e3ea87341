"""Trace one LLU update (eq 4) of OLiVia-Nav on doorway episodes: what the buffer holds, what the
update does to the text database D_T, and what it changes in the plan selection.

    python benchmarks/olivia_llu_trace.py --checkpoint runs/olivia/olivia.npz \\
        --adapt-seeds 310-329 --seeds 300-309 --trace-seeds 309 --out runs/llu_trace

1. **Before**: OLiVia-Nav drives every ``--seeds`` episode (the MSE / Hausdorff to the reference
   walker, reached). On the ``--trace-seeds`` every plan is recorded: the retrieved caption (its
   action, cosine similarity, whether it is an LLU view entry, whether E_T reached the TSM), the
   networks' log-scores, the selection's penalties and score per plan, the plan selected, and per
   plan its action (:func:`features.action_of`), where it ends (advance, lateral offset in the
   robot frame), whether it goes through the door (``through``), into a door post (``blocked``)
   or stops short of the door line (``short``), and (every ``--walker-every``-th plan) its mean
   squared distance to what the reference walker would do from that state.
2. **Buffer**: filled on ``--adapt-seeds`` as ``train.table_two`` does (``train.fill_buffer``),
   captioned (``train.caption_buffer``); per view its episode, head-on tag and caption. Kept in
   ``--buffer-cache`` (a pickle this script wrote) to rerun the update without re-driving.
3. **Update**: ``train.apply_llu``; D_T's size before / after and its new entries.
4. **Same states**: every traced plan of step 1 re-planned by the updated planner on the very same
   observation and context (the TPN's plans are the same: it keeps its encoder), so the change
   of the selected index is the update's alone.
5. **After**: the episodes again with the updated planner (traced like step 1).

Writes ``OUT/trace.json`` (everything above) and ``OUT/trace.md`` (a readable digest). Only for
development seeds: never point it at the held-out test seeds while choosing anything.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pickle
import sys
import time

import numpy as np


def parse_seeds(text: str) -> list[int]:
    """"300-302,309" -> [300, 301, 302, 309] (the social CLI's own seed parser)."""
    from splatsearch.social.olivia.cli import _ints

    return list(_ints(text))


def door_of(scn) -> tuple[float, float, float] | None:
    """(x, y_low, y_high) of the doorway's opening between the wall ends (the walls' centre
    lines; the clear width subtracts their radius), or None when the scene has no vertical wall
    pair with a gap (not a doorway)."""
    caps = np.asarray(scn.capsules, np.float64)
    vert = caps[np.isclose(caps[:, 0], caps[:, 2])]
    for x in np.unique(vert[:, 0]):
        w = vert[np.isclose(vert[:, 0], x)]
        if len(w) != 2:
            continue
        lo, hi = sorted(w.tolist(), key=lambda c: min(c[1], c[3]))
        y_lo, y_hi = max(lo[1], lo[3]), min(hi[1], hi[3])
        if y_hi > y_lo:
            return float(x), float(y_lo) + float(lo[4]), float(y_hi) - float(hi[4])
    return None


def door_passage(path_world: np.ndarray, door, robot_radius: float) -> str:
    """``through`` if the polyline ``path_world`` (N, 2) crosses the door's line inside the
    opening with the robot's body clear of both ends, ``blocked`` if it crosses it elsewhere,
    ``short`` if it does not reach it (or the scene has no door)."""
    if door is None:
        return "short"
    x, y_lo, y_hi = door
    p = np.asarray(path_world, np.float64)
    for a, b in zip(p[:-1], p[1:]):
        if (a[0] - x) * (b[0] - x) <= 0 and a[0] != b[0]:
            y = a[1] + (x - a[0]) / (b[0] - a[0]) * (b[1] - a[1])
            return "through" if y_lo + robot_radius <= y <= y_hi - robot_radius else "blocked"
    return "short"


def plan_geometry(trajs: np.ndarray, pose: np.ndarray, door, robot_radius: float) -> list[dict]:
    """Per plan ``trajs`` (K, horizon, 2 or 3) robot frame (x forward, y left, heading) from
    ``pose`` (3,) world: its action (:func:`features.action_of`), the advance / lateral offset of
    its end (m, lateral > 0 left) and its door passage (:func:`door_passage`)."""
    from splatsearch.social.convoi.geometry import robot_to_world
    from splatsearch.social.olivia.captions import ACTIONS
    from splatsearch.social.olivia.features import action_of

    out = []
    for tr in np.asarray(trajs, np.float64):
        w = robot_to_world(tr[:, :2], np.asarray(pose, np.float64))
        out.append({"action": ACTIONS[action_of(tr)], "advance": round(float(tr[-1, 0]), 3),
                    "lateral": round(float(tr[-1, 1]), 3),
                    "door": door_passage(np.vstack([np.asarray(pose, np.float64)[None, :2], w]), door, robot_radius)})
    return out


def walker_future(scn, rec: dict, horizon: int, stride: int) -> np.ndarray:
    """(horizon, 2) world: the reference walker's poses every ``stride`` steps forked from the
    traced state (held at its end)."""
    from splatsearch.social.convoi.human import walker_rollout

    poses = walker_rollout(scn, rec["pose"], rec["cmd"], rec["peds"], rec["t"], stride * horizon)
    idx = np.minimum(stride * np.arange(1, horizon + 1), len(poses) - 1)
    return np.asarray(poses, np.float64)[idx, :2]


def rescore(planner, rec: dict) -> dict:
    """The selection of ``planner`` on a traced state (the same observation, people seen,
    followed plan and clearance): selected index, score, the retrieved entry and its gate."""
    from splatsearch.social.olivia.selection import selection_scores

    obs = rec["obs"]
    res = planner.plan(obs.image, obs.points, obs.points_valid, obs.goal, person=rec.get("person"))
    parts = selection_scores(res.logits, rec["cand"], rec["pose"], rec["prev_world"], rec["elapsed"],
                             rec["seen_people"], rec["seen_vel"], rec["clearance"], planner.cfg)
    return {"index": int(np.argmax(parts["score"])), "score": parts["score"], "logits": res.logits,
            "retrieved": res.retrieved, "action": res.action, "similarity": res.similarity,
            "text_used": res.text_used}


def is_view_entry(db, j: int) -> bool:
    return db.keys is not None and bool(np.any(db.key_matrix[j] != db.embeddings[j]))


def plan_record(rec: dict, db, scn, door, walker_every: int, i: int) -> dict:
    """A JSON-able digest of one traced plan."""
    from splatsearch.social.convoi.scenarios import ROBOT_RADIUS
    from splatsearch.social.olivia.captions import ACTIONS
    from splatsearch.social.olivia.features import FUTURE_STRIDE

    geo = plan_geometry(rec["trajs"], rec["pose"], door, ROBOT_RADIUS)
    j = int(rec["retrieved"])
    out = {"t": int(rec["t"]), "time_s": round(rec["t"] * scn.dt, 2), "pose": [round(float(v), 3) for v in rec["pose"]],
           "oncoming": int(rec["oncoming"]), "retrieved": j, "retrieved_action": ACTIONS[rec["action"]] if rec["action"] >= 0 else "none",
           "similarity": round(float(rec["similarity"]), 4), "view_entry": is_view_entry(db, j),
           "text_used": bool(rec["text_used"]), "index": int(rec["index"]),
           "logits": np.round(np.asarray(rec["logits"], np.float64), 3).tolist(),
           "safety": np.round(rec["safety"], 3).tolist(), "consistency": np.round(rec["consistency"], 3).tolist(),
           "map": np.round(rec["map"], 3).tolist(), "score": np.round(rec["score"], 3).tolist(), "plans": geo}
    if walker_every > 0 and i % walker_every == 0:
        fut = walker_future(scn, rec, rec["cand"].shape[1], FUTURE_STRIDE)
        err = np.mean(np.sum((np.asarray(rec["cand"], np.float64) - fut[None]) ** 2, -1), -1)
        out["walker_mse"] = np.round(err, 4).tolist()
        out["walker_best"] = int(np.argmin(err))
        from splatsearch.social.convoi.geometry import world_to_robot

        out["walker"] = plan_geometry(world_to_robot(fut, np.asarray(rec["pose"], np.float64))[None], rec["pose"], door,
                                      ROBOT_RADIUS)[0]
    return out


def run_seed(planner, scenario: str, seed: int, trace: bool, walker_every: int, cache=None) -> tuple[dict, list, list]:
    """One episode: its metrics against the reference, and (``trace``) the raw trace and digest."""
    from splatsearch.social.convoi.runner import REFERENCE
    from splatsearch.social.convoi.scenarios import make_scenario
    from splatsearch.social.olivia.planner import run_olivia_episode
    from splatsearch.social.olivia.train import episode_metrics, run_baseline

    scn = make_scenario(scenario, seed)
    raw: list | None = [] if trace else None
    res = run_olivia_episode(scn, planner, trace=raw)
    ref = run_baseline(scn, REFERENCE, cache)
    m = episode_metrics(res, ref)
    metrics = {"seed": seed, "mse": float(m["mse"]), "haus": float(m["haus"]), "reached": bool(m["reached"]),
               "psv": float(m["psv"]), "final_y": float(res.robot[-1][1]),
               "min_y": float(np.min(res.robot[:, 1])), "ref_min_y": float(np.min(ref.robot[:, 1]))}
    digest = []
    if trace:
        door = door_of(scn)
        digest = [plan_record(r, planner.db, scn, door, walker_every, i) for i, r in enumerate(raw)]
    return metrics, raw or [], digest


def same_state_changes(before_raw: list, after_planner, db_after) -> list[dict]:
    """For every traced plan of the before-episode: the updated planner's selection there."""
    from splatsearch.social.olivia.captions import ACTIONS

    out = []
    for r in before_raw:
        a = rescore(after_planner, r)
        out.append({"t": int(r["t"]), "oncoming": int(r["oncoming"]), "index_before": int(r["index"]),
                    "index_after": a["index"], "retrieved_after": a["retrieved"],
                    "retrieved_action_after": ACTIONS[a["action"]] if a["action"] >= 0 else "none",
                    "similarity_after": round(a["similarity"], 4), "view_entry_after": is_view_entry(db_after, a["retrieved"]),
                    "text_used_after": a["text_used"],
                    "logits_after": np.round(np.asarray(a["logits"], np.float64), 3).tolist()})
    return out


def summarise_plans(digest: list[dict]) -> dict:
    n = max(len(digest), 1)
    on = [d for d in digest if d["oncoming"] > 0]
    chosen = lambda d: d["plans"][d["index"]]  # noqa: E731
    out = {"plans": len(digest), "text_used": sum(d["text_used"] for d in digest) / n,
           "oncoming_plans": len(on), "oncoming_text_used": sum(d["text_used"] for d in on),
           "chosen_actions": {}, "oncoming_chosen_actions": {}}
    for d in digest:
        a = chosen(d)["action"]
        out["chosen_actions"][a] = out["chosen_actions"].get(a, 0) + 1
    for d in on:
        a = chosen(d)["action"]
        out["oncoming_chosen_actions"][a] = out["oncoming_chosen_actions"].get(a, 0) + 1
    w = [d for d in digest if "walker_best" in d]
    if w:
        out["walker_best_chosen"] = sum(d["walker_best"] == d["index"] for d in w) / len(w)
        out["walker_checked"] = len(w)
    return out


def buffer_report(buf, captions) -> list[dict]:
    from splatsearch.social.olivia.captions import ACTIONS, action_from_text

    return [{"episode": int(e), "oncoming": int(o), "action": ACTIONS[a] if (a := action_from_text(c)) >= 0 else "none",
             "caption": c} for e, o, c in zip(buf.episodes, buf.oncoming, captions)]


def markdown(report: dict) -> str:
    L = [f"# LLU trace ({report['checkpoint']})", "", f"config overrides: {report['overrides']}", ""]
    L.append("| seed | MSE before | MSE after | reached before / after | min y before / after / ref |")
    L.append("|---|---|---|---|---|")
    before = {b["seed"]: b for b in report["before"]}
    for a in report.get("after", report["before"]):
        b = before.get(a["seed"], {"mse": float("nan"), "reached": None, "min_y": float("nan")})
        L.append(f"| {a['seed']} | {b['mse']:.4f} | {a['mse']:.4f} | {b['reached']} / {a['reached']} | "
                 f"{b['min_y']:.2f} / {a['min_y']:.2f} / {a['ref_min_y']:.2f} |")
    mb = np.mean([b["mse"] for b in report["before"]])
    L.append("")
    L.append(f"mean MSE before {mb:.4f}" + (f", after {np.mean([a['mse'] for a in report['after']]):.4f}"
                                           if report.get("after") else ""))
    if "buffer" in report:
        acts: dict[str, int] = {}
        on_acts: dict[str, int] = {}
        for v in report["buffer"]:
            acts[v["action"]] = acts.get(v["action"], 0) + 1
            if v["oncoming"]:
                on_acts[v["action"]] = on_acts.get(v["action"], 0) + 1
        eps: dict[int, int] = {}
        for v in report["buffer"]:
            eps[v["episode"]] = eps.get(v["episode"], 0) + 1
        L += ["", f"buffer: {len(report['buffer'])} views; actions {acts}; head-on tagged {on_acts}; per episode {eps}",
              f"D_T {report['db_before']} -> {report['db_after']}; eq 4 loss {report['llu_losses'][0]:.3f} -> "
              f"{report['llu_losses'][-1]:.3f}"]
    for seed, tr in report.get("traces", {}).items():
        for phase in ("before", "after"):
            if phase not in tr:
                continue
            L += ["", f"## seed {seed}, {phase}: {json.dumps(summarise_plans(tr[phase]))}", "",
                  "| t s | y | on | retrieved (sim, view, used) | chosen: action adv lat door | plans (action lat door, score) | walker best / its lat |",
                  "|---|---|---|---|---|---|---|"]
            for d in tr[phase]:
                c = d["plans"][d["index"]]
                plans = "; ".join(f"{p['action']} {p['lateral']:+.2f} {p['door']} {s:.1f}" for p, s in zip(d["plans"], d["score"]))
                wb = f"{d['walker_best']} / {d['walker']['lateral']:+.2f} {d['walker']['action']}" if "walker_best" in d else ""
                L.append(f"| {d['time_s']:.1f} | {d['pose'][1]:+.2f} | {d['oncoming']} | {d['retrieved_action']} "
                         f"({d['similarity']:.2f}, {'v' if d['view_entry'] else 't'}, {'y' if d['text_used'] else 'n'}) | "
                         f"{d['index']}: {c['action']} {c['advance']:.2f} {c['lateral']:+.2f} {c['door']} | {plans} | {wb} |")
        if "same_state" in tr:
            ss = tr["same_state"]
            ch = [s for s in ss if s["index_after"] != s["index_before"]]
            L += ["", f"seed {seed}, same states re-planned after the update: index changed on {len(ch)} of {len(ss)} "
                  f"(head-on: {sum(s['oncoming'] > 0 for s in ch)} of {sum(s['oncoming'] > 0 for s in ss)}); "
                  f"text used after on {sum(s['text_used_after'] for s in ss)}"]
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--scenario", default="doorway")
    ap.add_argument("--adapt-seeds", default="310-329", help="seeds the buffer is filled on (default 310-329)")
    ap.add_argument("--seeds", default="300-309", help="seeds measured before / after (default 300-309)")
    ap.add_argument("--trace-seeds", default="309", help="seeds whose every plan is recorded (default 309)")
    ap.add_argument("--size", type=int, default=50, help="|B| (default 50)")
    ap.add_argument("--buffer-every", type=int, default=2)
    ap.add_argument("--oncoming-share", type=float, default=0.5)
    ap.add_argument("--walker-every", type=int, default=0, help="every N-th traced plan: distance of each plan to the "
                    "reference walker's rollout from that state (0: off; it costs a rollout per plan)")
    ap.add_argument("--buffer-cache", default=None, help="pickle of the captioned buffer (read if it exists, else written)")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="override an OliviaConfig field (float / bool), e.g. --set safety=20")
    ap.add_argument("--no-after", action="store_true", help="stop after the before-episodes")
    ap.add_argument("--skip-before", action="store_true", help="run the before-episodes on the trace seeds only")
    ap.add_argument("--fresh-shift", action="store_true", help="caption with a walker forked with no lateral shift "
                    "(the captioner before stop 45) instead of the reference episode's shift at that step")
    ap.add_argument("--baseline-cache", default=None)
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)

    from splatsearch.social.olivia.llu import LLUBuffer, LLUConfig
    from splatsearch.social.olivia.planner import OliviaNav
    from splatsearch.social.olivia.train import apply_llu, caption_buffer, fill_buffer, load_planner
    from splatsearch.social.olivia.baseline_cache import BaselineCache

    t0 = time.time()
    planner = load_planner(args.checkpoint)
    overrides = {}
    for kv in args.set:
        k, v = kv.split("=", 1)
        cur = getattr(planner.cfg, k)
        overrides[k] = (v.lower() in ("1", "true", "yes")) if isinstance(cur, bool) else type(cur)(v)
    if overrides:
        planner = OliviaNav(planner.params, planner.db, dataclasses.replace(planner.cfg, **overrides), planner.variant)
    cache = BaselineCache(args.baseline_cache) if args.baseline_cache else None
    seeds, tseeds = parse_seeds(args.seeds), parse_seeds(args.trace_seeds)
    os.makedirs(args.out, exist_ok=True)
    report: dict = {"checkpoint": args.checkpoint, "overrides": overrides, "args": vars(args), "before": [], "traces": {}}
    raws: dict[int, list] = {}

    def save() -> None:  # after every stage, so that a run cut short keeps what it measured
        report["wall_s"] = time.time() - t0
        with open(os.path.join(args.out, "trace.json"), "w") as f:
            json.dump(report, f, indent=1, default=float)
        with open(os.path.join(args.out, "trace.md"), "w") as f:
            f.write(markdown(report))

    for s in (tseeds if args.skip_before else seeds):
        m, raw, dig = run_seed(planner, args.scenario, s, s in tseeds, args.walker_every, cache)
        report["before"].append(m)
        if s in tseeds:
            raws[s] = raw
            report["traces"][str(s)] = {"before": dig}
        print(f"before seed {s}: mse {m['mse']:.4f} reached {m['reached']} ({time.time() - t0:.0f} s)", flush=True)
        save()
    if not args.no_after:
        if args.buffer_cache and os.path.exists(args.buffer_cache):
            with open(args.buffer_cache, "rb") as f:
                d = pickle.load(f)
            buf = LLUBuffer(len(d["images"]))
            pers = d.get("persons", [None] * len(d["images"]))  # caches from before the person key have none
            for im, ob, on, ep, ps in zip(d["images"], d["observations"], d["oncoming"], d["episodes"], pers):
                buf.add(im, None, ob, on, ep, ps)
            captions, used = d["captions"], d["used"]
        else:
            buf, used = fill_buffer(planner, args.scenario, parse_seeds(args.adapt_seeds), args.size, args.buffer_every,
                                    args.oncoming_share, cache, carry_shift=not args.fresh_shift)
            captions = caption_buffer(buf)
            if args.buffer_cache:
                with open(args.buffer_cache, "wb") as f:
                    pickle.dump({"images": buf.images, "observations": buf.observations, "oncoming": buf.oncoming,
                                 "episodes": buf.episodes, "persons": buf.persons, "captions": captions, "used": used}, f)
        print(f"buffer: {len(buf.images)} views from {used} ({time.time() - t0:.0f} s)", flush=True)
        after, losses = apply_llu(planner, buf, captions, LLUConfig(size=args.size))
        n0 = len(planner.db.captions)
        report |= {"buffer": buffer_report(buf, captions), "db_before": n0, "db_after": len(after.db.captions),
                   "llu_losses": [float(x) for x in losses],
                   "new_entries": [{"index": j, "action": int(after.db.actions[j]), "view_entry": is_view_entry(after.db, j),
                                    "caption": after.db.captions[j]}
                                   for j in range(len(after.db.captions)) if j >= n0 or is_view_entry(after.db, j)][:200],
                   "after": []}
        save()
        for s in tseeds:
            if s in raws:
                report["traces"][str(s)]["same_state"] = same_state_changes(raws[s], after, after.db)
        save()
        for s in seeds:
            m, _, dig = run_seed(after, args.scenario, s, s in tseeds, args.walker_every, cache)
            report["after"].append(m)
            if s in tseeds:
                report["traces"][str(s)]["after"] = dig
            print(f"after seed {s}: mse {m['mse']:.4f} reached {m['reached']} ({time.time() - t0:.0f} s)", flush=True)
            save()
    save()
    print(markdown(report).split("\n## ")[0])
    return 0


if __name__ == "__main__":
    sys.exit(main())
