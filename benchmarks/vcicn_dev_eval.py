"""A small SR / SPL comparison of the completion variants on *development* houses.

The evaluation command (``splatsearch eval``) always uses evaluation houses (seeds 1000+), which
are never tuned on; this script runs the same episodes code on houses of the development range
(default seeds 900-903: neither training houses, 0-499, nor evaluation houses) so the variants
can be compared while developing.

    python benchmarks/vcicn_dev_eval.py --houses 900-903 --per-house 2 --workers 2 --out runs/vcicn_dev
"""

from __future__ import annotations

import argparse
import json
import os


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--houses", default="900-903", help="dev house seeds A-B, inside 500-999 (default: 900-903)")
    ap.add_argument("--per-house", type=int, default=2, help="val-hard episodes per house (default: 2)")
    ap.add_argument("--variants", default="splatsearch,no_vcicn,opencv_inpaint",
                    help="comma-separated variants (default: splatsearch,no_vcicn,opencv_inpaint)")
    ap.add_argument("--identical-furniture", action=argparse.BooleanOptionalAction, default=True,
                    help="look-alike houses (default: on)")
    ap.add_argument("--colour-cue", action=argparse.BooleanOptionalAction, default=False,
                    help="use the colour cue (default: off, feature matches alone)")
    ap.add_argument("--max-steps", type=int, default=None, help="step cap per episode (default: the episode's)")
    ap.add_argument("--workers", type=int, default=1, help="worker processes (default: 1)")
    ap.add_argument("--out", default="runs/vcicn_dev", help="output folder (default: runs/vcicn_dev)")
    args = ap.parse_args()

    from splatsearch import sim
    from splatsearch.evaluation import WORKER_MODULES, _run_one, markdown_table, summarise
    from splatsearch.io import atomic_write_bytes
    from splatsearch.parallel import Job, make_executor, warm_worker

    a, _, b = args.houses.partition("-")
    seeds = list(range(int(a), int(b or a) + 1))
    if any(not 500 <= s < 1000 for s in seeds):
        raise SystemExit("dev houses must be seeds 500-999 (0-499 train the VCICN, 1000+ are evaluation houses)")
    eps = []
    for s in seeds:
        house = sim.make_house(s, identical_furniture=args.identical_furniture)
        for e in sim.make_episodes(house, args.per_house, "val-hard", seed=0, env=sim.HouseEnv(house)):
            e.episode_id = len(eps)
            eps.append(e)
    variants = args.variants.split(",")
    over = {} if args.colour_cue else {"colour_cue": False}
    jobs = [Job(f"{e.episode_id}/{v}", _run_one, ((e.to_json(), v, args.max_steps, over),)) for e in eps for v in variants]
    os.makedirs(args.out, exist_ok=True)
    results = []
    threads = max(1, (os.cpu_count() or 1) // max(1, args.workers))
    with make_executor("local", args.workers, warmup=warm_worker, warmup_args=(threads, WORKER_MODULES)) as ex:
        for o in ex.run(jobs):
            r = o.value if o.ok else {"key": o.key, "error": o.error, "variant": o.key.split("/")[1],
                                      "success": False, "spl": 0.0, "steps": 0, "wall_time": o.wall_s}
            results.append(r)
            atomic_write_bytes(os.path.join(args.out, "results.json"), json.dumps(results, indent=1).encode())
            print(f"{o.key}: {'error' if 'error' in r else ('ok' if r['success'] else 'fail')}", flush=True)
    results.sort(key=lambda r: (r.get("episode_id", -1), variants.index(r["variant"])))
    summ = summarise(results)
    title = (f"dev houses {args.houses}, val-hard, {len(eps)} episodes"
             f"{', identical furniture' if args.identical_furniture else ''}"
             f"{'' if args.colour_cue else ', no colour cue'}")
    md = markdown_table(summ, title)
    atomic_write_bytes(os.path.join(args.out, "summary.md"), md.encode())
    atomic_write_bytes(os.path.join(args.out, "results.json"), json.dumps(results, indent=1).encode())
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
