"""``splatsearch vcicn data|train``: the VCICN's training data and training (no heavy imports
here; the handlers import what they need)."""

from __future__ import annotations

import argparse
import json
import math
import sys

from splatsearch.cli_types import positive_int


def _positive_float(text: str) -> float:
    v = float(text)
    if not v > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {v}")
    return v


def _nonnegative_float(text: str) -> float:
    v = float(text)
    if not (v >= 0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {v}")
    return v


def add_parser(sub) -> None:
    """Add the ``vcicn`` command to the ``splatsearch`` subparsers ``sub``."""
    p = sub.add_parser("vcicn", help="the view-completion network: make its training data, train it")
    vs = p.add_subparsers(dest="vcicn_command", required=True)

    d = vs.add_parser("data", help="render NVSM views of object-local maps and their simulator ground truth "
                                   "(one .npz shard per house)")
    d.add_argument("--houses", default="0-47",
                   help="training house seeds, 'A-B' inclusive or 'A,B,C', within 0-499 (evaluation houses are "
                        "1000+ and never used; default: 0-47)")
    d.add_argument("--out", default="runs/vcicn_data", help="output folder for the shards (default: runs/vcicn_data)")
    d.add_argument("--furniture", choices=["default", "identical", "both"], default="both",
                   help="house furniture mode: default, identical (one model per class) or both, i.e. every house "
                        "twice (default: both)")
    d.add_argument("--max-objects", type=positive_int, default=4,
                   help="goal-class objects per house at most (default: 4)")
    d.add_argument("--goal-views", type=int, default=2,
                   help="goal-image-style (val-hard) views per object besides the N_R hemisphere views (default: 2)")
    d.add_argument("--workers", type=positive_int, default=1,
                   help="worker processes (default: 1); a finished shard is skipped on a rerun")
    d.set_defaults(func=_cmd_data)

    t = vs.add_parser("train", help="train the VCICN on shards from `vcicn data` (optax AdamW; resumable)")
    t.add_argument("--data", default="runs/vcicn_data", help="folder of house_*.npz shards (default: runs/vcicn_data)")
    t.add_argument("--out", default="runs/vcicn", help="run folder: checkpoint.npz, best.npz, log.json "
                                                       "(default: runs/vcicn)")
    t.add_argument("--max-minutes", type=_positive_float, default=60.0,
                   help="wall-time budget in minutes; training stops (keeping the best checkpoint) when it is "
                        "spent (default: 60)")
    t.add_argument("--steps", type=positive_int, default=6000,
                   help="optimiser steps; the cosine learning-rate decay ends here (default: 6000)")
    t.add_argument("--batch", type=positive_int, default=2, help="objects per step (default: 2)")
    t.add_argument("--lr", type=_positive_float, default=2e-3, help="peak learning rate (default: 2e-3)")
    t.add_argument("--size", default="64x48", help="training resolution WxH in pixels, both divisible by 8 "
                                                   "(default: 64x48)")
    t.add_argument("--width", type=positive_int, default=16, help="channels of the first U-Net level, a multiple of 8 (default: 16)")
    t.add_argument("--eval-every", type=positive_int, default=400,
                   help="steps between validation passes and checkpoints (default: 400)")
    t.add_argument("--patience", type=positive_int, default=6,
                   help="validation passes without improvement before stopping early (default: 6)")
    t.add_argument("--val-houses", default=None,
                   help="held-apart validation house seeds ('A-B' or 'A,B'); default: seeds ending in 9")
    t.add_argument("--seed", type=int, default=0, help="initialisation and batch-order seed (default: 0)")
    t.add_argument("--grad-loss", type=_nonnegative_float, default=0.0,
                   help="weight of an L1 on image gradients of the completed views vs ground truth, which pays "
                        "for edges and texture in the fill (default: 0, off)")
    t.add_argument("--init", default=None,
                   help="start from these weights (.npz) instead of a random initialisation, e.g. the shipped "
                        "64x48 weights for a --size 128x96 run (same --width; default: none)")
    t.add_argument("--fresh", action="store_true", help="ignore an existing checkpoint in --out and start over")
    t.add_argument("--export", default=None,
                   help="also write the best weights (with provenance JSON beside them) to this .npz path")
    t.set_defaults(func=_cmd_train)


def _cmd_data(args: argparse.Namespace) -> int:
    from rich.console import Console

    from .data import DataConfig, generate, parse_houses

    seeds = parse_houses(args.houses)
    if args.goal_views < 0:
        raise ValueError(f"--goal-views must be >= 0, got {args.goal_views}")
    cfg = DataConfig(max_objects=args.max_objects, goal_views=args.goal_views)
    rep = generate(seeds, args.out, furniture=args.furniture, cfg=cfg, workers=args.workers)
    con = Console(stderr=True)
    con.print(f"wrote {rep['shards_written']} shard(s) (skipped {rep['shards_skipped']} finished): "
              f"{rep['objects']} objects, {rep['views']} views, {rep['MB']:.1f} MB in {rep['seconds']:.0f} s"
              + (f" ({rep['seconds_per_object']:.1f} worker-s per object)" if rep["seconds_per_object"] else ""))
    for e in rep["errors"]:
        con.print(f"[red]error[/red] {e}")
    print(json.dumps(rep))
    return 1 if rep["errors"] else 0


def _cmd_train(args: argparse.Namespace) -> int:
    from .train import TrainConfig, parse_size, train

    w, h = parse_size(args.size)
    cfg = TrainConfig(steps=args.steps, batch=args.batch, lr=args.lr, width=w, height=h, features=args.width,
                      eval_every=args.eval_every, patience=args.patience, max_minutes=args.max_minutes,
                      seed=args.seed, val_houses=args.val_houses, grad_weight=args.grad_loss, init=args.init)
    res = train(args.data, args.out, cfg, fresh=args.fresh, export=args.export,
                command="splatsearch " + " ".join(sys.argv[1:]))
    print(json.dumps(res))
    return 0
