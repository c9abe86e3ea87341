"""Score a Table II ``eval.json`` (``splatsearch social eval``) against a written LLU rule.

    python benchmarks/olivia_table2_rule.py EVAL.json [--drop 0.30] [--reached 10]

Passes iff the full model's mean MSE after one update is <= (1 - drop) x its mean before, at least
``--reached`` of its episodes reach the goal after, and every ablation's (w/o E_I, E_T, E_L) mean
MSE after is higher than the full model's after. Prints the verdict and exits 0 (pass) or 1 (fail).
"""
import argparse
import json
import sys

ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
ap.add_argument("eval_json")
ap.add_argument("--drop", type=float, default=0.30)
ap.add_argument("--reached", type=int, default=10)
a = ap.parse_args()
rows = {r["method"]: r for r in json.load(open(a.eval_json))["table2"]}
full = rows["OLiVia-Nav"]
abl = {k: r["mse_after"] for k, r in rows.items() if k != "OLiVia-Nav"}
drop_ok = full["mse_after"] <= (1 - a.drop) * full["mse_before"]
reach_ok = full["reached_after"] >= a.reached
abl_ok = len(abl) == 3 and all(v > full["mse_after"] for v in abl.values())
print(f"full {full['mse_before']:.4f} -> {full['mse_after']:.4f} ({100 * (full['mse_after'] / full['mse_before'] - 1):+.1f} %, "
      f"need <= {(1 - a.drop) * full['mse_before']:.4f}): {drop_ok}; reached after {full['reached_after']}/{full['n']}: "
      f"{reach_ok}; ablations after {({k: round(v, 4) for k, v in abl.items()})} all worse: {abl_ok}")
ok = drop_ok and reach_ok and abl_ok
print("PASS" if ok else "FAIL")
sys.exit(0 if ok else 1)
