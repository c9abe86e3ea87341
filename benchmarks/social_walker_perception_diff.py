"""Perceiving vs omniscient reference walker (stop 46): on given scenarios and seeds, the MSE
between the two walkers' paths (m²), their largest pose difference at equal steps (m), and when
the perceiving walker first knows each person (s).

Usage: python benchmarks/social_walker_perception_diff.py --specs hallway:60-61,doorway:300-309
[--baseline-cache DIR] (the perceiving episodes are read from / stored in the cache)."""

from __future__ import annotations

import argparse
import time

import numpy as np


def main(argv=None) -> int:
    from splatsearch.social.convoi.metrics import mse
    from splatsearch.social.convoi.runner import run_episode
    from splatsearch.social.convoi.scenarios import make_scenario
    from splatsearch.social.olivia.baseline_cache import BaselineCache
    from splatsearch.social.olivia.cli import _ints

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--specs", default="hallway:60-61,blind_corner:60-61,static_groups:60-67,dynamic_groups:60-63,"
                    "doorway:300-309", help="scenario:seeds, comma-separated (seeds as the social CLI reads them)")
    ap.add_argument("--baseline-cache", default=None)
    args = ap.parse_args(argv)
    cache = BaselineCache(args.baseline_cache) if args.baseline_cache else None
    specs, cur = [], None
    for part in args.specs.split(","):  # "doorway:300-309,329" keeps 329 with doorway
        if ":" in part:
            cur, part = part.split(":", 1)
            specs.append((cur, []))
        specs[-1][1].append(part)
    t0 = time.process_time()
    for name, parts in specs:
        for s in _ints(",".join(parts)):
            scn = make_scenario(name, s)
            p = cache.get(scn, "human", lambda: run_episode(scn, "human")) if cache else run_episode(scn, "human")
            o = run_episode(scn, "human_omniscient")
            n = min(len(p.robot), len(o.robot))
            first = sorted(round(float(np.argmax(p.detected[:, i])) * scn.dt, 1) if p.detected[:, i].any() else -1.0
                           for i in range(len(p.active)) if p.active[i])
            print(f"{name} {s}: MSE {mse(p.robot, o.robot):.4f} m^2, max |d pose| "
                  f"{np.abs(p.robot[:n, :2] - o.robot[:n, :2]).max():.2f} m, reached {p.reached}/{o.reached}, "
                  f"contacts {int(p.robot_contacts.sum())}/{int(o.robot_contacts.sum())}, first known at {first} s",
                  flush=True)
    print(f"cpu {time.process_time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
