"""How well a matcher separates the goal from its same-class look-alikes on stored NVSM views.

    python benchmarks/nvsm_separation.py runs/nvsm_views/dev --inpainter raw --inpainter opencv \\
        --matcher sift --matcher rootsift --out runs/nvsm_sep/dev.json
    python benchmarks/nvsm_separation.py runs/nvsm_views/eval --inpainter vcicn --matcher sift

Views come from ``benchmarks/nvsm_views.py``. For every (inpainter, matcher) row, each NVSM run's
views are completed (``raw``: the renders as rendered; ``opencv``: the stored OpenCV-inpainted
views; any other value: a :func:`splatsearch.plugins.make_inpainter` spec, run here on the stored
renders and hole masks, run by run as the NVSM does (an inpainter with ``completes_background``,
the VCICN, gets the interior holes and the cropped-away background, as ``verify_object`` gives
it; any other only the interior holes); a spec that cannot be built, e.g. an
inpainter kind this checkout does not have, skips its row with a message) and matched against the
goal image; an object's score is its best count over all views of all its runs, the NVSM's e_max.

Reported per row: ROC AUC of "goal vs same-class look-alike" from that score (positives: the goal
instance of each episode; negatives: every other instance of the goal's class that got views;
ties count half) with a bootstrap interval over episodes, the paired per-episode comparison
(goal's best count vs the best look-alike's: wins, ties, losses), the mean counts, and a
per-object table. ``--out`` writes everything as JSON (atomically).
"""

from __future__ import annotations

import argparse
import glob
import inspect
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from nvsm_views import _u8, load_views, split_views  # noqa: E402

#: inpainter choices that read stored views instead of building a plug-in
STORED = ("raw", "opencv")
#: --fill choices: the online map's renders (uncropped or cropped to the local map's region)
#: composited under the local map's before the holes are found, as ``AgentConfig.nvsm_fill`` does
FILLS = {"none": None, "global": ("grgb", "galpha"), "global-crop": ("gcrgb", "gcalpha")}


def apply_fill(d: dict, fill: str, alpha_tau: float = 0.5, crop_fill: float = 0.5) -> dict:
    """The episode arrays ``d`` as the NVSM would have seen them with ``fill`` (see :data:`FILLS`):
    the local map's renders (``local``, over black) composited over the stored online-map
    renders, holes found again at ``alpha_tau``, background greyed to ``crop_fill`` and the OpenCV
    views inpainted again (``split_views``), so every row scores the filled views. ``none``
    returns ``d`` unchanged. Needs a dump with ``local`` and the online-map renders."""
    from splatsearch.search.inpainting import OpenCVInpainter, holes_from_alpha
    from splatsearch.search.novel_views import composite_under

    if fill not in FILLS:
        raise ValueError(f"fill must be one of {list(FILLS)}, got {fill!r}")
    if FILLS[fill] is None:
        return d
    krgb, kalpha = FILLS[fill]
    if krgb not in d or "local" not in d:
        raise ValueError("this episode file has no online-map renders (dump it again with nvsm_views.py)")
    rgb, alpha = composite_under(d["local"].astype(np.float32) / 255.0, d["alpha"].astype(np.float32) / 255.0,
                                 d[krgb].astype(np.float32) / 255.0, d[kalpha].astype(np.float32) / 255.0)
    rendered, holes, background = split_views(rgb, holes_from_alpha(alpha, alpha_tau), alpha, alpha_tau, crop_fill)
    out = dict(d)
    out.update(rendered=_u8(rendered), alpha=_u8(alpha), holes=holes, background=background,
               opencv=_u8(OpenCVInpainter().inpaint(rendered, holes)))
    return out


def _views_of(d: dict, run: int, inpainter, name: str, holes_mode: str = "nvsm") -> np.ndarray:
    sel = d["view_run"] == run
    if name == "raw":
        return d["rendered"][sel]
    if name == "opencv":
        return d["opencv"][sel]
    rendered = d["rendered"][sel].astype(np.float32) / 255.0
    holes = d["holes"][sel]
    if holes_mode == "nvsm" and getattr(inpainter, "completes_background", False):
        # as the NVSM calls it (verify_object): a learned multi-view completion gets every hole,
        # the background cut away by the region crop included, not only the enclosed gaps
        holes = holes | d["background"][sel]
    extra = {"viewmats": d["viewmats"][sel], "alpha": d["alpha"][sel].astype(np.float32) / 255.0,
             "K": d["K"], "background": d["background"][sel]}
    try:
        params = inspect.signature(inpainter.inpaint).parameters
    except (TypeError, ValueError):
        params = {}
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        kw = extra
    else:
        kw = {k: v for k, v in extra.items() if k in params}
    return np.asarray(inpainter.inpaint(rendered, holes, **kw), np.float32)


def object_scores(files: list[str], matcher, inpainter_name: str, inpainter=None, progress=None,
                  holes_mode: str = "nvsm", fill: str = "none") -> list[dict]:
    """One record per (episode, instance): ``episode`` (file name), ``instance``, ``is_goal``,
    ``best`` (the best count over the views of all its runs), ``runs``, ``per_run`` (best per run).
    ``holes_mode``: "nvsm" (the masks the NVSM gives each inpainter) or "interior" (every plug-in
    gets only the enclosed holes). ``fill``: see :func:`apply_fill`."""
    from splatsearch.search.matching import best_view

    out = []
    for f in files:
        d = apply_fill(load_views(f), fill)
        goal = d["goal"]
        per: dict[int, dict] = {}
        for r in range(len(d["run_entry"])):
            views = _views_of(d, r, inpainter, inpainter_name, holes_mode)
            bv = best_view(goal, views, matcher)
            inst = int(d["run_instance"][r])
            rec = per.setdefault(inst, {"episode": os.path.basename(f), "instance": inst,
                                        "is_goal": bool(d["run_is_goal"][r]), "best": 0, "runs": 0, "per_run": []})
            rec["best"] = max(rec["best"], int(bv.e_max))
            rec["runs"] += 1
            rec["per_run"].append(int(bv.e_max))
            if progress:
                progress()
        out.extend(per.values())
    return out


def separation(records: list[dict]) -> dict:
    """ROC AUC and the paired per-episode comparison of :func:`object_scores` records.

    Returns ``auc`` (None without both classes), ``n_goal``, ``n_lookalike``, ``episodes`` (with
    a goal and at least one look-alike), ``wins`` / ``ties`` / ``losses`` (goal's best count vs
    the best look-alike's), ``mean_goal``, ``mean_lookalike``, ``mean_margin`` (goal minus best
    look-alike over paired episodes)."""
    from splatsearch.search.matching import roc_auc

    pos = [r["best"] for r in records if r["is_goal"]]
    neg = [r["best"] for r in records if not r["is_goal"]]
    by_ep: dict[str, dict] = {}
    for r in records:
        e = by_ep.setdefault(r["episode"], {"goal": None, "look": []})
        if r["is_goal"]:
            e["goal"] = r["best"]
        else:
            e["look"].append(r["best"])
    paired = [(e["goal"], max(e["look"])) for e in by_ep.values() if e["goal"] is not None and e["look"]]
    margins = [g - lk for g, lk in paired]
    return {"auc": roc_auc(pos, neg) if pos and neg else None, "n_goal": len(pos), "n_lookalike": len(neg),
            "episodes": len(paired), "wins": sum(m > 0 for m in margins), "ties": sum(m == 0 for m in margins),
            "losses": sum(m < 0 for m in margins),
            "mean_goal": float(np.mean(pos)) if pos else None, "mean_lookalike": float(np.mean(neg)) if neg else None,
            "mean_margin": float(np.mean(margins)) if margins else None}


def bootstrap_auc(records: list[dict], n: int = 2000, seed: int = 0, level: float = 0.95) -> tuple[float, float] | None:
    """A ``level`` percentile interval of the ROC AUC over episodes resampled with replacement
    (objects of one episode share a goal image, so they are resampled together); None without
    both classes."""
    from splatsearch.search.matching import roc_auc

    eps = sorted({r["episode"] for r in records})
    by = {e: [r for r in records if r["episode"] == e] for e in eps}
    rng = np.random.default_rng(seed)
    aucs = []
    for _ in range(n):
        recs = [r for i in rng.integers(0, len(eps), len(eps)) for r in by[eps[i]]]
        pos = [r["best"] for r in recs if r["is_goal"]]
        neg = [r["best"] for r in recs if not r["is_goal"]]
        if pos and neg:
            aucs.append(roc_auc(pos, neg))
    if not aucs:
        return None
    q = (1 - level) / 2
    return float(np.quantile(aucs, q)), float(np.quantile(aucs, 1 - q))


def build_inpainter(name: str):
    """None for the stored views; else the plug-in (raises what the plug-in loader raises)."""
    if name in STORED:
        return None
    from splatsearch.plugins import make_inpainter

    return make_inpainter(name)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("views", help="directory of episode .npz files from benchmarks/nvsm_views.py")
    ap.add_argument("--inpainter", action="append", default=None,
                    help="'raw' (renders as rendered), 'opencv' (the stored OpenCV-inpainted views) or an inpainter "
                         "spec of splatsearch.plugins (e.g. 'vcicn'); repeat for several rows (default: raw and opencv)")
    ap.add_argument("--matcher", action="append", default=None,
                    help="matcher spec of splatsearch.plugins, built for renders (e.g. 'sift', 'rootsift', "
                         "'features,model=essential'); repeat for several (default: sift)")
    ap.add_argument("--holes", choices=["nvsm", "interior"], default="nvsm",
                    help="holes a plug-in inpainter completes: 'nvsm' as the NVSM calls it (the VCICN also gets the "
                         "background cut away by the region crop) or 'interior' (enclosed holes only, background left "
                         "grey); default: nvsm")
    ap.add_argument("--fill", action="append", choices=list(FILLS), default=None,
                    help="composite the stored online-map renders under the local map's before completion, as "
                         "AgentConfig.nvsm_fill does: 'global' (uncropped), 'global-crop' (the local map's region); "
                         "repeat for several (default: none)")
    ap.add_argument("--per-object", action="store_true", help="print the per-object table of every row")
    ap.add_argument("--out", default=None, help="JSON file to write (atomically; default: none)")
    args = ap.parse_args(argv)
    files = sorted(glob.glob(os.path.join(args.views, "ep_*.npz")))
    if not files:
        ap.error(f"no ep_*.npz files in {args.views!r} (make them with benchmarks/nvsm_views.py)")
    inpainters = args.inpainter or ["raw", "opencv"]
    matchers = args.matcher or ["sift"]
    from rich.console import Console
    from rich.table import Table

    from splatsearch.plugins import make_matcher

    console = Console()
    n_runs = sum(len(np.load(f)["run_entry"]) for f in files)
    rows, skipped = [], []
    fills = args.fill or ["none"]
    for fill, inp_name in ((f, i) for f in fills for i in inpainters):
        try:
            inpainter = build_inpainter(inp_name)
        except (ValueError, FileNotFoundError, ImportError, OSError) as e:
            console.print(f"[yellow]skipping inpainter {inp_name!r}: {e}[/yellow]")
            skipped.append({"inpainter": inp_name, "reason": str(e)})
            continue
        for spec in matchers:
            matcher = make_matcher(spec, renders=True)
            t0 = time.perf_counter()
            recs = object_scores(files, matcher, inp_name, inpainter, holes_mode=args.holes, fill=fill)
            sep = separation(recs)
            sep["auc_ci95"] = bootstrap_auc(recs)
            row = {"inpainter": inp_name, "matcher": spec, "holes": args.holes, "fill": fill, **sep, "seconds": round(time.perf_counter() - t0, 1),
                   "load1": round(os.getloadavg()[0], 2), "objects": recs}
            rows.append(row)
            auc = "n/a" if sep["auc"] is None else f"{sep['auc']:.3f}"
            if sep["auc_ci95"] is not None:
                auc += " [{:.2f}, {:.2f}]".format(*sep["auc_ci95"])
            console.print(f"{fill:>11} | {inp_name:>8} | {spec:<40} | AUC {auc} | goal {sep['mean_goal']:.1f} vs look-alike "
                          f"{sep['mean_lookalike']:.1f} | paired W/T/L {sep['wins']}/{sep['ties']}/{sep['losses']} "
                          f"| {row['seconds']} s")
            if args.per_object:
                t = Table("episode", "instance", "goal?", "best", "per run")
                for r in recs:
                    t.add_row(r["episode"], str(r["instance"]), "goal" if r["is_goal"] else "", str(r["best"]),
                              " ".join(map(str, r["per_run"])))
                console.print(t)
    t = Table(title=f"{args.views}: {len(files)} episodes, {n_runs} NVSM runs")
    for c in ("fill", "inpainter", "matcher", "ROC AUC", "95% CI (episodes)", "goals", "look-alikes", "mean goal", "mean look-alike",
              "paired W/T/L"):
        t.add_column(c)
    for r in rows:
        ci = "n/a" if r["auc_ci95"] is None else "{:.2f}-{:.2f}".format(*r["auc_ci95"])
        t.add_row(r["fill"], r["inpainter"], r["matcher"], "n/a" if r["auc"] is None else f"{r['auc']:.3f}", ci, str(r["n_goal"]),
                  str(r["n_lookalike"]), f"{r['mean_goal']:.1f}", f"{r['mean_lookalike']:.1f}",
                  f"{r['wins']}/{r['ties']}/{r['losses']}")
    console.print(t)
    if args.out:
        from splatsearch.io import atomic_write_bytes

        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        atomic_write_bytes(args.out, json.dumps({"views": args.views, "files": [os.path.basename(f) for f in files],
                                                 "rows": rows, "skipped": skipped}, indent=1).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
