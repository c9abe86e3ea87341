"""Does the LLU's captioner agree with the reference along the reference's own path?

    python benchmarks/olivia_caption_vs_reference.py --seeds 300-309 --times 1-8 --out runs/capref.json

The LLU labels a view with ``features.expert_action``: the reference walker's rollout forked from
the robot's state (``human.walker_rollout``; since stop 45 with the lateral shift the reference
episode holds at that step, ``--shift carried``, the default; ``--shift fresh``: with none, the
captioner before, which undid the reference's head-on sidestep at 2-3 s). Tables I-II
score a planner against the reference's whole episode, in which the walker keeps the shift it
chose earlier (hysteresis, ``w_change``). For each seed, at each of ``--times`` (s) along the
reference episode, this prints the caption's action from the reference's own state and the action
of what the reference then did (its next 4 s, ``features.action_of``). Where the two differ, an
update that follows the captions moves the planner away from the reference.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np


def agreement(rows: list[dict]) -> dict:
    """Share of states where the caption's action equals the reference's own, overall and per
    reference action."""
    n = len(rows)
    per: dict[str, list] = {}
    for r in rows:
        per.setdefault(r["reference"], []).append(r["caption"] == r["reference"])
    return {"states": n, "agree": (sum(r["caption"] == r["reference"] for r in rows) / n) if n else float("nan"),
            "per_reference_action": {k: {"n": len(v), "agree": sum(v) / len(v)} for k, v in sorted(per.items())}}


def along_reference(scenario: str, seed: int, steps: list[int], cache=None, carry_shift: bool = True) -> list[dict]:
    """Caption action vs the reference's own action at the reference episode's ``steps``
    (``carry_shift``: the captioner's walker holds the reference's shift there, else none)."""
    import jax
    import jax.numpy as jnp

    from splatsearch.social.convoi import pedsim
    from splatsearch.social.convoi.runner import REFERENCE
    from splatsearch.social.convoi.scenarios import ROBOT_RADIUS, make_scenario
    from splatsearch.social.olivia.captions import ACTIONS
    from splatsearch.social.olivia.features import action_of, expert_action, extend_to_goal, future_in_frame
    from splatsearch.social.olivia.train import run_baseline

    scn = make_scenario(scenario, seed)
    ref = run_baseline(scn, REFERENCE, cache)
    caps, valid = scn.padded_capsules()
    caps, valid = jnp.asarray(caps), jnp.asarray(valid)
    sf = pedsim.SocialForceConfig(dt=scn.dt, robot_radius=ROBOT_RADIUS)
    key = jax.random.PRNGKey(scn.seed)
    peds = scn.peds
    poses = extend_to_goal(ref.robot, scn.goal) if ref.reached else ref.robot
    out = []
    last = min(max(steps, default=0), len(ref.cmds) - 1)
    for t in range(last + 1):
        if t in steps and t >= 1:
            off = float(ref.shifts[t]) if carry_shift and ref.shifts is not None else None
            # the perceiving walker forked here knows whom the reference knew (stop 46)
            known = ref.detected[t - 1] if ref.planner == "human" else None
            cap = expert_action(scn, ref.robot[t], ref.cmds[t - 1], peds, t, offset=off, seen=known)
            own = action_of(future_in_frame(poses, t, np.asarray(ref.robot[t], np.float64)))
            p = np.asarray(peds.pos)[0]
            out.append({"seed": seed, "t": t, "time_s": round(t * scn.dt, 2),
                        "robot": [round(float(v), 3) for v in ref.robot[t][:2]],
                        "person0": [round(float(v), 3) for v in p], "drift_check": float(np.abs(p - ref.people[t][0]).max()),
                        "shift": None if off is None else round(off, 3), "caption": ACTIONS[cap], "reference": ACTIONS[own]})
        # replay the people along the reference's moves (they react to the robot as they did)
        pose = ref.robot[t + 1]
        rv = float(ref.cmds[t][0]) * np.array([np.cos(pose[2]), np.sin(pose[2])], np.float32)
        peds, _ = pedsim.step(peds, caps, valid, jnp.asarray(pose[:2]), jnp.asarray(rv), pedsim.step_key(key, t), sf)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="doorway")
    ap.add_argument("--seeds", default="300-309")
    ap.add_argument("--times", default="1-8", help="whole seconds along the reference episode (default 1-8)")
    ap.add_argument("--shift", choices=("carried", "fresh"), default="carried",
                    help="the captioner's walker holds the reference's shift at that step (carried, the LLU's "
                         "captioner since stop 45) or none (fresh, the one before) (default carried)")
    ap.add_argument("--baseline-cache", default=None)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    from olivia_llu_trace import parse_seeds

    from splatsearch.social.olivia.baseline_cache import BaselineCache

    cache = BaselineCache(args.baseline_cache) if args.baseline_cache else None
    steps = [10 * s for s in parse_seeds(args.times)]
    rows: list[dict] = []
    t0 = time.time()
    for seed in parse_seeds(args.seeds):
        r = along_reference(args.scenario, seed, steps, cache, carry_shift=args.shift == "carried")
        rows += r
        print(seed, " | ".join(f"{x['time_s']:.0f}s {x['caption']}/{x['reference']}" for x in r),
              f"({time.time() - t0:.0f} s)", flush=True)
        if args.out:
            with open(args.out, "w") as f:
                json.dump({"rows": rows, "summary": agreement(rows)}, f, indent=1)
    print(json.dumps(agreement(rows), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
