"""Closed loop with an oracle D_T (a bound on one LLU update, dev doorway seeds). At every plan, D_T gets one
extra entry keyed by the view's own E_I (so it is retrieved at cosine 1 and passes every gate):
the template caption of that state with the captioner's action (the reference walker forked with
the reference's carried shift, the LLU's default captioner since stop 45). This is the best any
LLU update acting through E_T could do with this TPN / TSM / selection: if it does not move seed
309, no buffer or retrieval fix will.

Usage: python benchmarks/olivia_oracle_dt.py --checkpoint T0/olivia.npz --seeds 309,304 --out OUT.json [--baseline-cache DIR]
[--after-seen]

Only for development seeds: it runs the privileged captioner on the evaluated episode itself.
The state the captioner needs is read through ``olivia_episode_fork`` (the planner module's hooks
wrapped in this process only); the episode loop itself is the library's, unchanged.
"""
import argparse
import json
import os
import sys
import time

import numpy as np

from splatsearch.social.convoi.runner import REFERENCE
from splatsearch.social.convoi.scenarios import make_scenario
from splatsearch.social.olivia import planner as pm
from splatsearch.social.olivia.captions import ACTIONS, TemplateCaptioner, caption_scene
from splatsearch.social.olivia.features import action_of, expert_action
from splatsearch.social.olivia.llu import add_view_entries
from splatsearch.social.olivia.train import (encode_all_images, encode_all_texts, episode_metrics, load_planner,
                                             reference_shift_of, run_baseline)
from splatsearch.social.olivia.baseline_cache import BaselineCache

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from olivia_episode_fork import install, reset  # noqa: E402

ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
ap.add_argument("--checkpoint", required=True)
ap.add_argument("--seeds", default="309", help="doorway dev seeds, comma list (default 309)")
ap.add_argument("--baseline-cache", default=None)
ap.add_argument("--after-seen", action="store_true", help="the oracle entry only from the first plan at which the "
                "robot perceives someone ahead (person_key.person_state): the bound of any retrieval keyed by "
                "the robot's perception of people")
ap.add_argument("--out", required=True)
args = ap.parse_args()
ck, out, seeds = args.checkpoint, args.out, [int(s) for s in args.seeds.split(",")]
cache = BaselineCache(args.baseline_cache) if args.baseline_cache else None
base = load_planner(ck)
clip = base.params["clip"]
cap = TemplateCaptioner()

state = install()


class Oracle:
    """A planner whose D_T also holds, for the current view, its right caption (keyed by its own E_I)."""

    def __init__(self, scn):
        self.cfg, self.variant, self.scn = base.cfg, base.variant, scn
        self.shift = reference_shift_of(scn, cache)
        self.log = []
        self.seen = False

    def plan(self, image, points, points_valid, goal, prior=None, person=None):
        scn, t = self.scn, state["t"]
        self.seen = self.seen or (person is not None and not np.all(np.isnan(person)))
        if args.after_seen and not self.seen:
            res = base.plan(image, points, points_valid, goal, prior, person)
            self.log.append({"t": t, "y": round(float(state["pose"][1]), 3), "caption_action": "none",
                             "used": bool(res.text_used), "tsm_best": int(res.index),
                             "tsm_best_action": ACTIONS[action_of(res.trajs[res.index])]})
            return res
        act = expert_action(scn, state["pose"], state["cmd"], state["peds"], t, offset=self.shift(t))
        sc = caption_scene(scn, state["pose"], np.asarray(state["peds"].pos), np.asarray(state["peds"].vel), act)
        c = cap.caption(image, sc).long
        img = (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)[None]
        db = add_view_entries(base.db, encode_all_images(clip, img, base.cfg.clip),
                              encode_all_texts(clip, [c], base.cfg.clip), [c])
        res = pm.OliviaNav(base.params, db, base.cfg, base.variant).plan(image, points, points_valid, goal, prior, person)
        self.log.append({"t": t, "y": round(float(state["pose"][1]), 3), "caption_action": ACTIONS[act],
                         "used": bool(res.text_used), "tsm_best": int(res.index),
                         "tsm_best_action": ACTIONS[action_of(res.trajs[res.index])]})
        return res


rows = []
t0 = time.time()
for seed in seeds:
    scn = make_scenario("doorway", seed)
    reset(scn)
    o = Oracle(scn)
    res = pm.run_olivia_episode(scn, o)
    m = episode_metrics(res, run_baseline(scn, REFERENCE, cache))
    rows.append({"seed": seed, "mse": float(m["mse"]), "haus": float(m["haus"]), "reached": bool(m["reached"]),
                 "min_y": float(np.min(res.robot[:, 1])), "plans": o.log})
    acts: dict = {}
    for p in o.log:
        acts[p["caption_action"]] = acts.get(p["caption_action"], 0) + 1
    print(f"seed {seed}: mse {m['mse']:.4f} haus {m['haus']:.3f} reached {m['reached']} min y {rows[-1]['min_y']:.2f} "
          f"captions {acts} ({time.time() - t0:.0f} s)", flush=True)
    print("  first 4 s:", " ".join(f"{p['t'] / 10:.1f}:{p['caption_action'][:6]}>{p['tsm_best_action'][:6]}@{p['y']:+.2f}"
                                   for p in o.log if p["t"] <= 40), flush=True)
    json.dump({"rows": rows, "wall_s": time.time() - t0}, open(out, "w"), indent=1)
