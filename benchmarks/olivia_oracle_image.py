"""Closed loop with an oracle E_I and an oracle plan selection (the bound of any F_I update, dev doorway seeds).

Rule 0 of stop 47 (``olivia_oracle_selection.py``) bounded every caption route: the selection told
the plan nearest the reference's future among the TPN's K plans as they are. But E_I = F_I(view)
is an input of the TPN (eq 1), and eq 4 updates F_I, so an update could change the plans
themselves. This script bounds that: at every plan the TPN is run (same LiDAR sweeps, same goal
features) on every E_I of a bank, and the oracle takes the (E_I, plan) pair whose plan is nearest
(mean squared position error over the horizon) to the reference walker's own future from that
state (the perceiving walker forked with the reference episode's carried shift and the people
the robot has perceived so far, as in rule 0). The robot drives that plan: the networks' logits
are replaced by 0 for it and -1000 for the other plans of that E_I, so consistency / safety /
map terms cannot overrule it.

The bank (every entry is some view's E_I, i.e. a point on the encoder's manifold):

- ``own``: the current view through the TPN's F_I (no update: rule 0's oracle is this entry alone);
- ``own_llu``: the current view through F_I after one LLU update (eq 4 on ``--buffer-cache``'s
  50 views and captions, ``train.apply_llu``: what an update actually does to this view's E_I);
- ``buffer`` / ``buffer_llu``: the buffer's 50 adaptation-doorway views through F_I / F_I';
- ``train`` / ``train_llu``: up to ``--per-kind`` training views of every (scene kind, caption
  action) cell (scene kinds: the five scenarios, doorway split into plain 200-205 and head-on
  220-238), drawn by ``--bank-seed``, through F_I / F_I'.

With ``--with-before`` each seed is also driven by the unmodified planner (its MSE is the
"before" the bound is compared with). Per plan the log holds the nearest error of the ``own``
entry, of the whole bank, and the kind / scene / action of the winning entry.

Usage: python benchmarks/olivia_oracle_image.py --checkpoint T0/olivia.npz --seeds 309,302 \\
    --buffer-cache buf46.pkl --baseline-cache DIR --out OUT.json [--with-before] [--per-kind 4]

Only for development seeds: it runs the reference walker on the evaluated episode itself. It
decides nothing by itself; the state the walker needs is read through ``olivia_episode_fork``.
"""
import argparse
import dataclasses
import json
import os
import pickle
import sys
import time

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from splatsearch.social.convoi.human import HumanWalkerConfig, walker_rollout
from splatsearch.social.convoi.perception import visible_people
from splatsearch.social.convoi.runner import GOAL_TOLERANCE, REFERENCE
from splatsearch.social.convoi.scenario_names import SCENARIOS
from splatsearch.social.convoi.scenarios import make_scenario
from splatsearch.social.olivia import planner as pm
from splatsearch.social.olivia.baseline_cache import BaselineCache
from splatsearch.social.olivia.captions import ACTIONS
from splatsearch.social.olivia.dataset import HEADON_DOOR_SEEDS
from splatsearch.social.olivia.features import FUTURE_STRIDE, HORIZON, action_of, extend_to_goal, future_in_frame
from splatsearch.social.olivia.llu import LLUBuffer, LLUConfig
from splatsearch.social.olivia.sc_clip import SCCLIP, normalize
from splatsearch.social.olivia.tpn import TPN, CrossLayer, GRUHead, LidarEncoder, TPNConfig
from splatsearch.social.olivia.train import (apply_llu, encode_all_images, episode_metrics, load_planner,
                                             reference_shift_of, run_baseline)

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from olivia_episode_fork import install, reset  # noqa: E402

ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
ap.add_argument("--checkpoint", required=True)
ap.add_argument("--seeds", default="309", help="doorway dev seeds, comma list, run in this order")
ap.add_argument("--samples", default=None, help="training samples npz of the bank (default: beside the checkpoint)")
ap.add_argument("--per-kind", type=int, default=4, help="training views per (scene kind, action) cell")
ap.add_argument("--bank-seed", type=int, default=0)
ap.add_argument("--buffer-cache", required=True, help="olivia_llu_trace.py's buffer pickle (views + captions)")
ap.add_argument("--baseline-cache", default=None)
ap.add_argument("--with-before", action="store_true", help="also drive each seed with the unmodified planner")
ap.add_argument("--max-steps", type=int, default=None, help="cut episodes short (a smoke test only)")
ap.add_argument("--out", required=True)
args = ap.parse_args()
seeds = [int(s) for s in args.seeds.split(",")]
cache = BaselineCache(args.baseline_cache) if args.baseline_cache else None
base = load_planner(args.checkpoint)
walker_cfg = HumanWalkerConfig(perceive=REFERENCE == "human")
state = install()
t_start = time.time()


def to_u8(im: np.ndarray) -> np.ndarray:
    return im if im.dtype == np.uint8 else (np.clip(im, 0, 1) * 255 + 0.5).astype(np.uint8)


# --- one LLU update on the dev buffer (what eq 4 does to F_I) ---
with open(args.buffer_cache, "rb") as f:
    d = pickle.load(f)
buf = LLUBuffer(len(d["images"]))
for im, ob, on, ep, ps in zip(d["images"], d["observations"], d["oncoming"], d["episodes"], d["persons"]):
    buf.add(im, None, ob, on, ep, ps)
after, _ = apply_llu(base, buf, d["captions"], LLUConfig(size=len(d["images"])))
clip0 = base.params.get("clip_tpn", base.params["clip"])  # the F_I the TPN was trained with
clip1 = after.params["clip"]  # F_I after one update
ccfg = base.cfg.clip
print(f"LLU update done ({time.time() - t_start:.0f} s)", flush=True)

# --- the bank ---
samples = args.samples or os.path.join(os.path.dirname(args.checkpoint), "samples_train.npz")
z = np.load(samples)
sc, sd, act = z["scenario"], z["seed"], z["action"]
kind_of = np.array([("headon_doorway" if (SCENARIOS[s] == "doorway" and k in HEADON_DOOR_SEEDS) else SCENARIOS[s])
                    for s, k in zip(sc, sd)])
rng = np.random.default_rng(args.bank_seed)
pick = []
for kd in sorted(set(kind_of)):
    for a in range(len(ACTIONS)):
        idx = np.flatnonzero((kind_of == kd) & (act == a))
        if len(idx):
            pick += sorted(rng.choice(idx, min(args.per_kind, len(idx)), replace=False).tolist())
pick = np.asarray(pick)
train_imgs = z["image"][pick]
buf_imgs = np.stack([to_u8(im) for im in buf.images])
fixed = np.concatenate([encode_all_images(clip0, train_imgs, ccfg), encode_all_images(clip1, train_imgs, ccfg),
                        encode_all_images(clip0, buf_imgs, ccfg), encode_all_images(clip1, buf_imgs, ccfg)])
meta = ([{"kind": "train", "scene": str(kind_of[i]), "action": ACTIONS[int(act[i])], "row": int(i)} for i in pick]
        + [{"kind": "train_llu", "scene": str(kind_of[i]), "action": ACTIONS[int(act[i])], "row": int(i)} for i in pick]
        + [{"kind": "buffer", "scene": f"adapt {d['episodes'][i]}", "action": "", "row": i} for i in range(len(buf_imgs))]
        + [{"kind": "buffer_llu", "scene": f"adapt {d['episodes'][i]}", "action": "", "row": i} for i in range(len(buf_imgs))])
meta = [{"kind": "own", "scene": "this view", "action": "", "row": -1},
        {"kind": "own_llu", "scene": "this view", "action": "", "row": -1}] + meta
B = len(meta)
print(f"bank: {B} E_I ({len(pick)} training views x 2 encoders, {len(buf_imgs)} buffer views x 2, own x 2)", flush=True)


@jax.jit
def encode_both(image):
    e0 = normalize(SCCLIP(ccfg).apply({"params": clip0}, image[None], method=SCCLIP.encode_image))
    e1 = normalize(SCCLIP(ccfg).apply({"params": clip1}, image[None], method=SCCLIP.encode_image))
    return jnp.concatenate([e0, e1])


class TPNFromLidar(nn.Module):
    """The TPN's forward pass (tpn.TPN, image and LiDAR on, no scores) with the LiDAR tokens
    given, so the LiDAR encoder runs once per plan instead of once per bank entry (same
    parameter names; checked against tpn.TPN on the first plan)."""

    cfg: TPNConfig

    @nn.compact
    def __call__(self, e_img, lid, goal):
        c = self.cfg
        n = e_img.shape[0]
        img = nn.Dense(c.img_tokens * c.C)(nn.relu(nn.Dense(c.C)(e_img))).reshape(n, c.img_tokens, c.C)
        lid = jnp.broadcast_to(lid, (n,) + lid.shape[1:])
        g = nn.relu(nn.Dense(c.C, name="goal_ffn")(goal))[:, None]
        q = jnp.broadcast_to(self.param("query", nn.initializers.normal(1.0), (1, c.K, c.C), jnp.float32), (n, c.K, c.C))
        q = CrossLayer(c.C, c.heads, name="sc_clip_attn")(q, img, jnp.ones(img.shape[:2], bool))
        q = CrossLayer(c.C, c.heads, name="lidar_attn")(q, lid, jnp.ones(lid.shape[:2], bool))
        q = CrossLayer(c.C, c.heads, name="goal_attn")(q, g, jnp.ones((n, 1), bool))
        heads = nn.vmap(GRUHead, variable_axes={"params": 0}, split_rngs={"params": True}, in_axes=1, out_axes=1,
                        axis_size=c.K)
        return heads(c, name="tfh")(q)


tpn_p = base.params["tpn"]
tpn_sub = {k: v for k, v in tpn_p.items() if k not in ("LidarEncoder_0", "score_ffn", "score_out")}


@jax.jit
def plans_of(e_bank, points, valid, goal):
    """(B, K, horizon, 3) plans of the TPN for every E_I of ``e_bank`` (B, D) with one observation."""
    lid = LidarEncoder(base.cfg.tpn).apply({"params": tpn_p["LidarEncoder_0"]}, points[None], valid[None])
    return TPNFromLidar(base.cfg.tpn).apply({"params": tpn_sub}, e_bank, lid,
                                            jnp.broadcast_to(goal, (e_bank.shape[0],) + goal.shape))


@jax.jit
def plans_full(e_bank, points, valid, goal):
    n = e_bank.shape[0]
    on = jnp.ones((n,), bool)
    return TPN(base.cfg.tpn).apply({"params": tpn_p}, e_bank, jnp.broadcast_to(points, (n,) + points.shape),
                                   jnp.broadcast_to(valid, (n,) + valid.shape),
                                   jnp.broadcast_to(goal, (n,) + goal.shape), on, on)


fixed_j = jnp.asarray(fixed, jnp.float32)


class Oracle:
    """The trained planner whose E_I is any bank entry and whose selection is told the nearest plan."""

    def __init__(self, scn):
        self.cfg, self.variant, self.scn = base.cfg, base.variant, scn
        self.shift = reference_shift_of(scn, cache)
        caps, valid = scn.padded_capsules()
        self.caps, self.valid = jnp.asarray(caps), jnp.asarray(valid)
        self.known = np.zeros(len(np.asarray(scn.peds.active)), bool)
        self.log = []
        self.checked = False

    def plan(self, image, points, points_valid, goal, prior=None, person=None):
        scn, t, pose, peds = self.scn, state["t"], state["pose"], state["peds"]
        self.known |= np.asarray(visible_people(jnp.asarray(pose), jnp.asarray(peds.pos), jnp.asarray(scn.peds.active),
                                                self.caps, self.valid))
        res = base.plan(image, points, points_valid, goal, prior, person)
        bank = jnp.concatenate([encode_both(jnp.asarray(image)), fixed_j])
        trajs = np.asarray(plans_of(bank, jnp.asarray(points, jnp.float32), jnp.asarray(points_valid),
                                    jnp.asarray(goal, jnp.float32)), np.float64)  # (B, K, H, 3)
        if not self.checked:  # the shortcut is the TPN: on a few entries, and the own entry is the planner's plans
            sel = jnp.asarray([0, 1, B - 1])
            full = np.asarray(plans_full(bank[sel], jnp.asarray(points, jnp.float32), jnp.asarray(points_valid),
                                         jnp.asarray(goal, jnp.float32)))
            assert np.abs(full - trajs[np.asarray(sel)]).max() < 1e-3, np.abs(full - trajs[np.asarray(sel)]).max()
            assert np.abs(trajs[0] - res.trajs).max() < 1e-3, np.abs(trajs[0] - res.trajs).max()
            self.checked = True
        poses = walker_rollout(scn, pose, state["cmd"], peds, t, FUTURE_STRIDE * HORIZON, walker_cfg,
                               offset=self.shift(t), seen=self.known.copy())
        if np.linalg.norm(poses[-1, :2] - np.asarray(scn.goal)[:2]) < GOAL_TOLERANCE:
            poses = extend_to_goal(poses, scn.goal)
        fut = future_in_frame(poses, 0, np.asarray(pose, np.float64))
        err = np.mean(np.sum((trajs[..., :2] - fut[None, None, :, :2]) ** 2, -1), -1)  # (B, K)
        b, k = np.unravel_index(int(np.argmin(err)), err.shape)
        own_k = int(np.argmin(err[0]))
        self.log.append({"t": t, "y": round(float(pose[1]), 3), "net_best": int(res.index),
                         "own_err": round(float(err[0, own_k]), 4), "bank_err": round(float(err[b, k]), 4),
                         "net_err": round(float(err[0, res.index]), 4), "entry": int(b), **meta[b],
                         "plan_end_y": round(float(trajs[b, k, -1, 1]), 3),
                         "own_max_end_y": round(float(np.max(trajs[0, :, -1, 1])), 3),
                         "bank_max_end_y": round(float(np.max(trajs[:, :, -1, 1])), 3),
                         "ref_end_y": round(float(fut[-1, 1]), 3), "ref_action": ACTIONS[action_of(fut)]})
        logits = np.full(trajs.shape[1], -1000.0, np.float32)
        logits[k] = 0.0
        return dataclasses.replace(res, trajs=trajs[b].astype(np.float32), logits=logits, index=int(k))


rows = []
t0 = time.time()
for seed in seeds:
    scn = make_scenario("doorway", seed)
    ref = run_baseline(scn, REFERENCE, cache)
    row = {"seed": seed}
    if args.with_before:
        reset(scn)
        m0 = episode_metrics(pm.run_olivia_episode(scn, base, max_steps=args.max_steps), ref)
        row |= {"before": float(m0["mse"]), "before_reached": bool(m0["reached"])}
    reset(scn)
    o = Oracle(scn)
    res = pm.run_olivia_episode(scn, o, max_steps=args.max_steps)
    m = episode_metrics(res, ref)
    kinds: dict = {}
    for p in o.log:
        kinds[p["kind"]] = kinds.get(p["kind"], 0) + 1
    row |= {"mse": float(m["mse"]), "haus": float(m["haus"]), "reached": bool(m["reached"]),
            "max_y": float(np.max(res.robot[:, 1])), "ref_max_y": float(np.max(np.asarray(ref.robot)[:, 1])),
            "kinds": kinds, "mean_own_err": float(np.mean([p["own_err"] for p in o.log])),
            "mean_bank_err": float(np.mean([p["bank_err"] for p in o.log])), "plans": o.log}
    rows.append(row)
    print(f"seed {seed}: before {row.get('before', float('nan')):.4f} E_I-oracle mse {m['mse']:.4f} haus "
          f"{m['haus']:.3f} reached {m['reached']} max y {row['max_y']:+.2f} (ref {row['ref_max_y']:+.2f}); "
          f"nearest-plan err own {row['mean_own_err']:.4f} bank {row['mean_bank_err']:.4f}; entries {kinds} "
          f"({time.time() - t0:.0f} s)", flush=True)
    json.dump({"rows": rows, "bank": meta, "wall_s": time.time() - t0, "checkpoint": args.checkpoint,
               "per_kind": args.per_kind, "bank_seed": args.bank_seed}, open(args.out, "w"), indent=1)
if rows:
    mean = np.mean([r["mse"] for r in rows])
    line = f"{len(rows)} seeds: E_I-oracle mean {mean:.4f}"
    if args.with_before:
        mb = np.mean([r["before"] for r in rows])
        line += f", before mean {mb:.4f} ({100 * (mean / mb - 1):+.0f} %)"
    print(line, flush=True)
