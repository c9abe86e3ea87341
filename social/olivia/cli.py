"""``splatsearch social data``, ``social train`` and ``social eval`` (OLiVia-Nav).

``data`` and ``eval``'s Table I run as independent jobs on local worker processes or a Ray
cluster (``--backend``, ``--address``, ``--workers``; see :mod:`splatsearch.parallel`).

Wire into the social CLI with :func:`register_olivia`::

    sub = social_parser.add_subparsers(dest="social_cmd")
    register_olivia(sub)
    args = parser.parse_args(); args.func(args)
"""

from __future__ import annotations

import argparse
import json
import os
import time


def _ints(text: str) -> tuple[int, ...]:
    """"0-5" or "1000,1001" -> a tuple of ints."""
    out: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        if "-" in part:
            a, b = part.split("-", 1)
            out += list(range(int(a), int(b) + 1))
        else:
            out.append(int(part))
    if not out or any(s < 0 for s in out):
        raise argparse.ArgumentTypeError(f"expected seeds like '0-5' or '1000,1001', got {text!r}")
    return tuple(out)


def _ints_or_none(text: str) -> tuple[int, ...]:
    """Like :func:`_ints`, and "none" -> ()."""
    return () if text.strip().lower() == "none" else _ints(text)


def _scenarios(text: str) -> tuple[str, ...]:
    from ..convoi.scenario_names import SCENARIOS

    names = tuple(s.strip() for s in text.split(",") if s.strip())
    bad = [n for n in names if n not in SCENARIOS]
    if bad or not names:
        raise argparse.ArgumentTypeError(f"unknown scenario(s) {bad}; choose from {', '.join(SCENARIOS)}")
    return names


def register_olivia(social_subparsers) -> None:
    """Add the ``data``, ``train`` and ``eval`` sub-subcommands (handlers set with ``set_defaults(func=...)``)."""
    from splatsearch.parallel import add_executor_args

    from ..convoi.scenario_names import (DOOR_TRAIN_SEEDS, LLU_ADAPT_SEEDS, LLU_TEST_SEEDS, TABLE_ONE_SEEDS,
                                         THESIS_SCENARIOS)

    d = social_subparsers.add_parser("data", help="expert episodes + renders -> OUT/samples_{train,val}.npz, in "
                                                  "parallel (then `social train --out OUT` uses them)")
    d.add_argument("--out", default="runs/olivia", help="output directory (default runs/olivia)")
    d.add_argument("--scenarios", type=_scenarios, default=THESIS_SCENARIOS, help="comma list (default: Table I's four)")
    d.add_argument("--train-seeds", type=_ints, default=tuple(range(6)), help="e.g. 0-5 (default) or 0,3")
    d.add_argument("--val-seeds", type=_ints, default=(50,), help="default 50")
    d.add_argument("--door-seeds", type=_ints_or_none, default=DOOR_TRAIN_SEEDS,
                   help=f"doorway scenes (sampled door widths) added to the training split, as social train does "
                        f"(default: {DOOR_TRAIN_SEEDS[0]}-{DOOR_TRAIN_SEEDS[-1]}; 'none': no doorways)")
    # a literal (dataset.HEADON_DOOR_SEEDS's module pulls in JAX) kept equal to it by a test
    d.add_argument("--headon-door-seeds", type=_ints_or_none, default=tuple(range(220, 233)) + tuple(range(234, 239)),
                   help="head-on doorway scenes (the person meets the robot just past the door; the reference "
                        "yields or passes) added to the training split, as social train does (default: 220-232,234-238; "
                        "'none': none)")
    d.add_argument("--every", type=int, default=5, help="sample an expert state every N sim steps")
    d.add_argument("--augment", type=int, default=1, help="displaced copies per expert state")
    d.add_argument("--resume", action="store_true", help="keep the finished episodes in OUT/parts/, run the rest")
    d.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_executor_args(d, default_workers=None)
    d.set_defaults(func=cmd_data)

    p = social_subparsers.add_parser("train", help="train OLiVia-Nav (SC-CLIP, TPN, TSM) on expert episodes")
    p.add_argument("--out", default="runs/olivia", help="output directory (checkpoints, data cache, summary)")
    p.add_argument("--scenarios", type=_scenarios, default=THESIS_SCENARIOS,
                   help=f"comma list of scenarios (default: {','.join(THESIS_SCENARIOS)})")
    p.add_argument("--train-seeds", type=_ints, default=tuple(range(6)), help="training seeds, e.g. 0-5 (default: 0-5)")
    p.add_argument("--val-seeds", type=_ints, default=(50,), help="validation seeds for early stopping (default: 50)")
    # literals (not TrainConfig's, whose module pulls in JAX) kept equal to TrainConfig by a test
    p.add_argument("--clip-epochs", type=int, default=16, help="SC-CLIP epochs at most")
    p.add_argument("--tpn-epochs", type=int, default=15, help="TPN epochs at most")
    p.add_argument("--tsm-epochs", type=int, default=40, help="TSM epochs at most")
    p.add_argument("--patience", type=int, default=5, help="epochs without a better validation loss before stopping")
    p.add_argument("--every", type=int, default=5, help="sample an expert state every N sim steps")
    p.add_argument("--augment", type=int, default=1, help="displaced copies per expert state")
    p.add_argument("--seed", type=int, default=0, help="training seed (initialisation, shuffling)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_train)

    e = social_subparsers.add_parser("eval", help="OLiVia-Nav vs DWA vs CoNVOI+DWA (Table I) and ablations with LLU (Table II)")
    e.add_argument("--checkpoint", default="runs/olivia/olivia.npz", help="checkpoint written by social train")
    e.add_argument("--out", default=None, help="where to write eval.json and eval.md (default: next to the checkpoint)")
    e.add_argument("--scenarios", type=_scenarios, default=THESIS_SCENARIOS,
                   help=f"comma list of scenarios (default: {','.join(THESIS_SCENARIOS)})")
    e.add_argument("--seeds", type=_ints, default=TABLE_ONE_SEEDS,
                   help=f"held-out seeds, never trained on (default: {TABLE_ONE_SEEDS[0]}-{TABLE_ONE_SEEDS[-1]})")
    e.add_argument("--baselines", default="dwa,convoi", help="comma list of dwa, convoi (or empty)")
    e.add_argument("--ablations", action="store_true", help="also the ablations in Table I")
    e.add_argument("--llu-scenario", type=_scenarios, default=("doorway",),
                   help="held-out scenario for Table II (default: doorway)")
    e.add_argument("--llu-adapt-seeds", type=_ints, default=LLU_ADAPT_SEEDS,
                   help=f"seeds driven in order until the buffer holds --llu-size images "
                        f"(default: {LLU_ADAPT_SEEDS[0]}-{LLU_ADAPT_SEEDS[-1]})")
    e.add_argument("--llu-test-seeds", type=_ints, default=LLU_TEST_SEEDS,
                   help=f"seeds Table II is measured on (default: {LLU_TEST_SEEDS[0]}-{LLU_TEST_SEEDS[-1]})")
    e.add_argument("--llu-size", type=int, default=50, help="LLU buffer size |B| in images")
    e.add_argument("--llu-mu", type=float, default=0.05, help="eq 4 temperature")
    e.add_argument("--llu-tpn-encoder", choices=("trained", "updated"), default="trained",
                   help="the F_I that gives the TPN its E_I after an update: the one it was trained with "
                        "(default) or the updated one (the thesis)")
    e.add_argument("--llu-caption-keep", type=float, default=0.35,
                   help="m: a buffer view is captioned keep left / right when the reference's 4 s future ends more "
                        "than this far to the side (default 0.35, the training data's threshold; only the LLU "
                        "buffer's captions change)")
    e.add_argument("--llu-oncoming-share", type=float, default=0.5,
                   help="0: the buffer is the first --llu-size views of the adaptation seeds, in order; in (0, 1]: "
                        "every adaptation seed is driven and the buffer keeps up to this share of views with a person "
                        "walking head-on toward the robot, the rest spread over all episodes")
    e.add_argument("--llu-buffer-every", type=int, default=2, help="every N-th plan offers its view to the buffer")
    e.add_argument("--no-table2", action="store_true", help="skip Table II (the LLU update)")
    e.add_argument("--no-table1", action="store_true", help="skip Table I (only Table II)")
    e.add_argument("--llu-ablations-after-only", action="store_true",
                   help="Table II: run the ablations only after the update (the full model before and after)")
    e.add_argument("--no-progress", action="store_true", help="no progress bars")
    e.add_argument("--resume", action="store_true", help="keep Table I's finished jobs in OUT/table1_jobs.json")
    e.add_argument("--baseline-cache", default=None, metavar="DIR",
                   help="cache the reference, DWA and CoNVOI+DWA episodes in DIR, keyed by scenario, seed, geometry "
                        "and a SHA-256 of the convoi sources, so later evaluations (other trainings) reuse them")
    e.add_argument("--route-berth", type=float, default=None, metavar="M",
                   help="plan selection: the route (goal features, fallback) keeps M metres from people standing "
                        "still and never crosses a standing group, as the walker's does (default: the checkpoint's, "
                        "0 = the walls-only path)")
    e.add_argument("--perceived-berth", type=float, default=None, metavar="M",
                   help="plan selection: the route keeps M metres from the standing people the robot has perceived "
                        "(in line of sight within sensing range, measured nearly still) and never crosses a group "
                        "of them; re-routed when that set changes (default: the checkpoint's or 0.8; 0 = the "
                        "walls-only path; --route-berth > 0 takes precedence)")
    e.add_argument("--cross-tau", type=float, default=None, metavar="S",
                   help="plan selection: time constant (s) with which the drift across the line to the robot of a "
                        "person walking at it head-on decays in the safety forecast (default: the checkpoint's; "
                        "0 = constant velocity)")
    e.add_argument("--people-react", type=float, default=None, metavar="G",
                   help="plan selection: in the safety forecast, people ahead of the robot make way for it, moving "
                        "sideways off its line of travel at rate G (1/s) until 0.95 m (centre to centre) from it "
                        "(default: the checkpoint's; 0 = constant velocity)")
    add_executor_args(e, default_workers=None)
    e.set_defaults(func=cmd_eval)


def _progress(disabled: bool):
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                    TimeElapsedColumn(), disable=disabled)


def _job_task(prog, name: str):
    """A progress task that follows an executor's counts (done / running / failed)."""
    tid = prog.add_task(name, total=None)
    return lambda c: prog.update(tid, total=c.total, completed=c.done,
                                 description=f"{name} (running {c.running}, failed {c.failed})")


def cmd_data(args) -> int:
    from rich.console import Console

    from splatsearch.parallel import executor_from_args

    from .jobs import build_datasets

    if args.every < 1 or args.augment < 0:
        raise SystemExit("--every must be >= 1 and --augment >= 0")
    if set(args.train_seeds) & set(args.val_seeds):
        raise SystemExit("train and validation seeds overlap")
    from ..convoi.scenario_names import LLU_ADAPT_SEEDS, LLU_TEST_SEEDS

    held = (set(args.door_seeds) | set(args.headon_door_seeds)) & (set(LLU_ADAPT_SEEDS) | set(LLU_TEST_SEEDS))
    if held:
        raise SystemExit(f"--door-seeds / --headon-door-seeds {sorted(held)} are the held-out doorway's "
                         "adaptation or test seeds")
    if "doorway" in args.scenarios and set(args.train_seeds) & set(args.door_seeds):
        raise SystemExit("--door-seeds overlap --train-seeds of the doorway scenario")
    with executor_from_args(args) as ex, _progress(args.no_progress) as prog:
        sizes = build_datasets(args.out, args.scenarios, {"train": args.train_seeds, "val": args.val_seeds},
                               every=args.every, augment=args.augment, executor=ex, resume=args.resume,
                               on_update=_job_task(prog, "expert episodes"), vary_geometry=True,
                               door_seeds=args.door_seeds, headon_door_seeds=args.headon_door_seeds,
                               perceived_berth=0.8)  # TrainConfig.perceived_berth (a test keeps them equal)
    Console().print(f"{sizes['train']} train / {sizes['val']} val samples -> {args.out}/samples_train.npz, "
                    "samples_val.npz")
    return 0


def cmd_train(args) -> int:
    from rich.console import Console

    from .train import TrainConfig, train_olivia

    for name in ("clip_epochs", "tpn_epochs", "tsm_epochs", "patience", "every"):
        if getattr(args, name) < 1:
            raise SystemExit(f"--{name.replace('_', '-')} must be >= 1")
    if set(args.train_seeds) & set(args.val_seeds):
        raise SystemExit("train and validation seeds overlap")
    tc = TrainConfig(scenarios=tuple(args.scenarios), train_seeds=tuple(args.train_seeds),
                     val_seeds=tuple(args.val_seeds), every=args.every, augment=args.augment,
                     clip_epochs=args.clip_epochs, tpn_epochs=args.tpn_epochs, tsm_epochs=args.tsm_epochs,
                     patience=args.patience, seed=args.seed)
    console = Console()
    with _progress(args.no_progress) as prog:
        summary = train_olivia(args.out, tc, log=console.log, progress=prog)
    console.print(f"trained in {summary['seconds']:.0f} s -> {os.path.join(args.out, 'olivia.npz')}")
    return 0


def cmd_eval(args) -> int:
    from rich.console import Console

    from splatsearch.parallel import executor_from_args

    from .llu import LLUConfig
    from .jobs import table_one_parallel
    from .train import format_table_one, format_table_two, load_planner, table_two

    console = Console()
    if not 0.0 <= args.llu_oncoming_share <= 1.0 or args.llu_buffer_every < 1 or args.llu_size < 2:
        console.print("[red]--llu-oncoming-share must be in [0, 1], --llu-buffer-every >= 1, --llu-size >= 2[/]")
        return 2
    if args.no_table1 and args.no_table2:
        console.print("[red]--no-table1 and --no-table2 leave nothing to evaluate[/]")
        return 2
    if set(args.llu_adapt_seeds) & set(args.llu_test_seeds):
        console.print("[red]--llu-adapt-seeds and --llu-test-seeds overlap[/]")
        return 2
    cache = None
    if args.baseline_cache:
        from .baseline_cache import BaselineCache

        try:
            cache = BaselineCache(args.baseline_cache)
        except (ValueError, OSError) as exc:
            console.print(f"[red]--baseline-cache: {exc}[/]")
            return 2
    overrides = {}
    if args.route_berth is not None:
        if not args.route_berth >= 0:
            console.print("[red]--route-berth must be >= 0 metres[/]")
            return 2
        overrides["route_berth"] = float(args.route_berth)
    if args.perceived_berth is not None:
        if not args.perceived_berth >= 0:
            console.print("[red]--perceived-berth must be >= 0 metres[/]")
            return 2
        overrides["perceived_berth"] = float(args.perceived_berth)
    if args.cross_tau is not None:
        if not args.cross_tau >= 0:
            console.print("[red]--cross-tau must be >= 0 seconds[/]")
            return 2
        overrides["cross_tau"] = float(args.cross_tau)
    if args.people_react is not None:
        if not args.people_react >= 0:
            console.print("[red]--people-react must be >= 0 (1/s)[/]")
            return 2
        overrides["people_react"] = float(args.people_react)
    planner = load_planner(args.checkpoint)
    if overrides:
        import dataclasses

        from .planner import OliviaNav

        planner = OliviaNav(planner.params, planner.db, dataclasses.replace(planner.cfg, **overrides))
    out = args.out or os.path.dirname(os.path.abspath(args.checkpoint))
    os.makedirs(out, exist_ok=True)
    baselines = tuple(b for b in args.baselines.split(",") if b)
    for b in baselines:
        if b not in ("dwa", "convoi"):
            raise SystemExit(f"unknown baseline {b!r}; choose from dwa, convoi")
    variants = ("olivia", "no_image", "no_text", "no_lidar") if args.ablations else ("olivia",)
    if set(args.seeds) & set(range(0, 100)):
        console.print("[yellow]warning: seeds below 100 overlap the default training/validation seeds[/]")
    t0 = time.perf_counter()
    result: dict = {"checkpoint": args.checkpoint, "seeds": list(args.seeds), "overrides": overrides}
    with _progress(args.no_progress) as prog, executor_from_args(args) as ex:
        md = ""
        if not args.no_table1:
            rows = table_one_parallel(args.checkpoint, args.scenarios, args.seeds, baselines, variants, executor=ex,
                                      out_dir=out, resume=args.resume, on_update=_job_task(prog, "Table I"),
                                      log=console.log, cache_dir=cache.directory if cache else None,
                                      overrides=overrides)
            result["table1"] = rows
            md = "## Table I (held-out seeds " + ", ".join(map(str, args.seeds)) + ")\n\n" + format_table_one(rows)
        if not args.no_table2:
            llu = LLUConfig(size=args.llu_size, mu=args.llu_mu, tpn_encoder=args.llu_tpn_encoder,
                            caption_keep=args.llu_caption_keep)
            rows2, _, info = table_two(planner, args.llu_scenario[0], args.llu_adapt_seeds, args.llu_test_seeds, llu,
                                       log=console.log, progress=prog, cache=cache,
                                       buffer_every=args.llu_buffer_every, oncoming_share=args.llu_oncoming_share,
                                       before_variants=("olivia",) if args.llu_ablations_after_only else None)
            result["table2"] = rows2
            result["llu"] = info
            ef = info["effect"]
            md += (f"\n\n## Table II ({args.llu_scenario[0]}, held out of training; |B| = {info['buffer']} from "
                   f"adaptation seeds {', '.join(map(str, info['adapt_seeds']))}, {info['buffer_oncoming']} of its views with "
                   f"a person walking head-on toward the robot, i_t = 1)\n\n" + format_table_two(rows2)
                   + f"\n\nLLU (eq 4): loss {info['llu_losses'][0]:.3f} -> {info['llu_losses'][-1]:.3f}; buffer captions' "
                   f"actions {ef['caption_actions']}; |D_T| {info['db_before']} -> {info['db_after']}; on the "
                   f"{ef['views']} buffer views the retrieved caption's action matches the new caption "
                   f"{ef['retrieved_action_right_before']:.2f} -> {ef['retrieved_action_right_after']:.2f}, the TSM's "
                   f"selected plan performs it {ef['plan_action_right_before']:.2f} -> "
                   f"{ef['plan_action_right_after']:.2f}, selected index changed on "
                   f"{ef['selected_index_changed']:.2f} of them.")
    result["seconds"] = time.perf_counter() - t0
    with open(os.path.join(out, "eval.json"), "w", encoding="utf-8") as f:
        json.dump(result, f, indent=1)
    with open(os.path.join(out, "eval.md"), "w", encoding="utf-8") as f:
        f.write(md + "\n")
    console.print(md)
    return 0
