"""Probe (dev seed 309, training 0): if D_T retrieved, for the very view, a caption with action A
(keyed by the view's own E_I, so it passes the gate at cosine 1), which plan would the selection
choose? Does any caption move the choice off plan 3 toward the keep-right plans at 0-3 s?

Usage: python benchmarks/olivia_forced_caption.py CHECKPOINT OUT.json [SEED] [T_MAX_S]

Open loop: the states of the before-episode are re-scored, not driven. Dev seeds only.
"""
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from olivia_llu_trace import rescore  # noqa: E402

from splatsearch.social.convoi.scenarios import make_scenario  # noqa: E402
from splatsearch.social.olivia.captions import ACTIONS, TemplateCaptioner, caption_scene  # noqa: E402
from splatsearch.social.olivia.features import action_of  # noqa: E402
from splatsearch.social.olivia.llu import add_view_entries  # noqa: E402
from splatsearch.social.olivia.planner import OliviaNav, run_olivia_episode  # noqa: E402
from splatsearch.social.olivia.train import encode_all_images, encode_all_texts, load_planner  # noqa: E402

ck, out = sys.argv[1], sys.argv[2]
seed = int(sys.argv[3]) if len(sys.argv) > 3 else 309
tmax = float(sys.argv[4]) if len(sys.argv) > 4 else 3.0
t0 = time.time()
planner = load_planner(ck)
scn = make_scenario("doorway", seed)
raw: list = []
run_olivia_episode(scn, planner, trace=raw)
cap = TemplateCaptioner()
clip = planner.params["clip"]
rows = []
for r in raw:
    if r["t"] * scn.dt > tmax + 1e-9:
        break
    obs = r["obs"]
    img = (np.clip(obs.image, 0, 1) * 255 + 0.5).astype(np.uint8)[None]
    e_i = encode_all_images(clip, img, planner.cfg.clip)
    peds = r["peds"]
    row = {"t_s": round(r["t"] * scn.dt, 2), "y": round(float(r["pose"][1]), 3), "index_before": int(r["index"]),
           "plan_actions": [ACTIONS[action_of(tr)] for tr in r["trajs"]],
           "plan_lateral": [round(float(tr[-1, 1]), 2) for tr in r["trajs"]], "forced": {}}
    for a in ("keep_right", "turn_right", "yield", "straight", "keep_left"):
        sc = caption_scene(scn, r["pose"], np.asarray(peds.pos), np.asarray(peds.vel), ACTIONS.index(a))
        c = cap.caption(obs.image, sc).long
        db = add_view_entries(planner.db, e_i, encode_all_texts(clip, [c], planner.cfg.clip), [c])
        p2 = OliviaNav(planner.params, db, planner.cfg, planner.variant)
        s = rescore(p2, r)
        row["forced"][a] = {"index": s["index"], "used": bool(s["text_used"]), "sim": round(float(s["similarity"]), 3),
                            "retrieved_action": ACTIONS[s["action"]],
                            "logits": np.round(np.asarray(s["logits"], np.float64), 2).tolist()}
    rows.append(row)
    print(row["t_s"], row["y"], row["index_before"], row["plan_actions"],
          {a: (v["index"], v["retrieved_action"], v["used"]) for a, v in row["forced"].items()}, flush=True)
json.dump({"seed": seed, "rows": rows, "wall_s": time.time() - t0}, open(out, "w"), indent=1)
print(f"{time.time() - t0:.0f} s")
