"""Summarise a `splatsearch eval` results.json: SR, SPL, median wall time and paired wins.

Only episodes that every listed variant finished are counted, so a partial (resumable) run gives
numbers over a common set of episodes. Paired W/T/L counts success per episode; the two-sided
exact sign test (McNemar on the discordant pairs) says how surprising the split would be if both
variants were equally good.

    python benchmarks/sr_summary.py runs/sr100/results.json --variants splatsearch,no_vcicn,no_nvsm
"""

from __future__ import annotations

import argparse
import json
import math
from collections import defaultdict
from pathlib import Path
from statistics import median


def load_rows(path: Path) -> list[dict]:
    """Rows of a results.json (a list of per-run dicts with house_seed, episode_id, variant)."""
    rows = json.loads(path.read_text())
    if not isinstance(rows, list):
        raise SystemExit(f"{path}: expected a JSON list of per-run rows, got {type(rows).__name__}")
    return rows


def sign_test_p(wins: int, losses: int) -> float:
    """Two-sided exact binomial p-value of `wins` vs `losses` discordant pairs under p = 0.5."""
    n = wins + losses
    if n == 0:
        return 1.0
    k = min(wins, losses)
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2.0**n
    return min(1.0, 2.0 * tail)


def summarise(rows: list[dict], variants: list[str]) -> dict:
    """Per-variant SR/SPL/median wall and pairwise paired W/T/L over the common episodes."""
    by_ep: dict[tuple[int, int], dict[str, dict]] = defaultdict(dict)
    for r in rows:
        by_ep[(int(r["house_seed"]), int(r["episode_id"]))][r["variant"]] = r
    common = sorted(k for k, v in by_ep.items() if all(x in v for x in variants))
    out: dict = {"episodes": len(common), "houses": sorted({h for h, _ in common}), "variants": {}}
    for v in variants:
        runs = [by_ep[k][v] for k in common]
        out["variants"][v] = {
            "sr": sum(bool(r["success"]) for r in runs) / max(len(runs), 1),
            "spl": sum(float(r["spl"]) for r in runs) / max(len(runs), 1),
            "median_wall_s": median(float(r["wall_time"]) for r in runs) if runs else float("nan"),
        }
    pairs = {}
    for i, a in enumerate(variants):
        for b in variants[i + 1:]:
            w = sum(bool(by_ep[k][a]["success"]) and not by_ep[k][b]["success"] for k in common)
            l_ = sum(bool(by_ep[k][b]["success"]) and not by_ep[k][a]["success"] for k in common)
            pairs[f"{a} vs {b}"] = {"wins": w, "ties": len(common) - w - l_, "losses": l_,
                                    "sr_step": out["variants"][a]["sr"] - out["variants"][b]["sr"],
                                    "sign_test_p": sign_test_p(w, l_)}
    out["pairs"] = pairs
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("results", type=Path, help="results.json written by `splatsearch eval --out DIR`")
    ap.add_argument("--variants", default="splatsearch,no_vcicn,no_nvsm",
                    help="comma-separated variants, best first (pairs are formed in this order)")
    ap.add_argument("--json", action="store_true", help="print the summary as JSON instead of tables")
    args = ap.parse_args()
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    s = summarise(load_rows(args.results), variants)
    if args.json:
        print(json.dumps(s, indent=2))
        return
    print(f"{s['episodes']} episodes all variants finished, houses {s['houses']}")
    print("| variant | SR | SPL | median wall s |\n|---|---|---|---|")
    for v, m in s["variants"].items():
        print(f"| {v} | {m['sr']:.3f} | {m['spl']:.3f} | {m['median_wall_s']:.1f} |")
    print("\n| pair | W/T/L | SR step | sign-test p |\n|---|---|---|---|")
    for p, m in s["pairs"].items():
        print(f"| {p} | {m['wins']}/{m['ties']}/{m['losses']} | {m['sr_step']:+.3f} | {m['sign_test_p']:.3f} |")


if __name__ == "__main__":
    main()
