"""The lateral drift distribution of an LLU buffer's captions (no update, no scoring).

    python benchmarks/olivia_buffer_drift.py --checkpoint CKPT [--adapt-seeds 310-329] [--baseline-cache DIR]

Fills the Table II buffer exactly as ``social eval`` does (doorway, |B| 50, every 2nd plan,
oncoming share 0.5, the reference's carried shift) and records, for each kept view, where the
reference's 4 s future (the captioner's label) ends to the side (robot frame, m, + left) and its
action at the training threshold (0.35 m). Prints the distribution and writes it as JSON.
This is what an LLU buffer caption threshold may be fixed from before any scoring run.
"""
import argparse
import json

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--scenario", default="doorway")
    ap.add_argument("--adapt-seeds", default="310-329")
    ap.add_argument("--size", type=int, default=50)
    ap.add_argument("--buffer-every", type=int, default=2)
    ap.add_argument("--oncoming-share", type=float, default=0.5)
    ap.add_argument("--baseline-cache", default=None)
    ap.add_argument("--out", required=True)
    a = ap.parse_args()

    from splatsearch.social.olivia import features, planner as planner_mod
    from splatsearch.social.olivia.baseline_cache import BaselineCache
    from splatsearch.social.olivia.captions import ACTIONS
    from splatsearch.social.olivia.train import fill_buffer, load_planner

    rows: list[dict] = []

    def recording_action(scn, pose, vel, peds, t, world=None, reference=None, offset=None, seen=None,
                         keep=features.KEEP_THRESHOLD):
        fut = features.expert_future(scn, pose, vel, peds, t, world, reference, offset, seen)
        act = features.action_of(fut, keep)
        rows.append({"seed": int(scn.seed), "t": int(t), "end_y": float(fut[-1, 1]), "end_x": float(fut[-1, 0]),
                     "end_yaw": float(fut[-1, 2]), "action": ACTIONS[act]})
        return act

    planner_mod.expert_action = recording_action  # the lazy buffer's scenes call it for the kept views only
    lo, hi = (int(x) for x in a.adapt_seeds.split("-"))
    cache = BaselineCache(a.baseline_cache) if a.baseline_cache else None
    buf, used = fill_buffer(load_planner(a.checkpoint), a.scenario, range(lo, hi + 1), a.size, a.buffer_every,
                            a.oncoming_share, cache)
    assert len(rows) == len(buf.scenes) == a.size, (len(rows), len(buf.scenes))
    y = np.array([r["end_y"] for r in rows])
    straight = np.array([r["action"] == "straight" for r in rows])
    counts = {k: sum(r["action"] == k for r in rows) for k in ACTIONS}
    out = {"checkpoint": a.checkpoint, "adapt_seeds": a.adapt_seeds, "views": rows, "actions_at_0.35": counts,
           "abs_end_y_straight_median": float(np.median(np.abs(y[straight]))) if straight.any() else None,
           "end_y_quantiles": {q: float(np.quantile(y, q)) for q in (0.1, 0.25, 0.5, 0.75, 0.9)}}
    json.dump(out, open(a.out, "w"), indent=1)
    print("actions at 0.35 m:", counts)
    print("end y of the straight views (m):", np.round(np.sort(y[straight]), 3).tolist())
    print("median |end y| of the straight views:", out["abs_end_y_straight_median"])
    print("end y quantiles (all views):", out["end_y_quantiles"])


if __name__ == "__main__":
    main()
