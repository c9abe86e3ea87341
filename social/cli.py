"""``splatsearch social``: run DWA and CoNVOI + DWA on the social scenarios and print the tables.

    splatsearch social --scenario hallway|...|all --seeds K [--viewer] [--port 8080]
    splatsearch social run ...        (the same, as an explicit sub-command)

``register(subparsers)`` adds the ``social`` parser to a top-level ``argparse`` sub-parser set; the
handler is set with ``set_defaults(func=...)`` and returns the exit status. Room is left for
``social train`` / ``social eval`` (further sub-commands of ``social``).
"""

from __future__ import annotations

import argparse
import json
import os

from .convoi.scenario_names import SCENARIOS


def _add_run_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", default="all", help=f"one of {', '.join(SCENARIOS)}, a comma list, or 'all'")
    p.add_argument("--seeds", type=int, default=2, help="seeds per scenario (>= 1)")
    p.add_argument("--seed-offset", type=int, default=0, help="first seed (>= 0)")
    p.add_argument("--methods", default="dwa,convoi", help="comma list of dwa, convoi (the expert always runs)")
    p.add_argument("--vlm", choices=["rules", "openai", "replay"], default="rules",
                   help="CoNVOI's large VLM: offline rules, an OpenAI-compatible endpoint, or a recording")
    p.add_argument("--vlm-url", default=None, help="base URL of the OpenAI-compatible endpoint (…/v1)")
    p.add_argument("--vlm-model", default="gpt-4o", help="model name for --vlm openai")
    p.add_argument("--vlm-record", default=None,
                   help="JSON file: record the VLM's answers (with --vlm openai/rules) or replay them (--vlm replay)")
    p.add_argument("--latency", type=float, default=0.0, help="simulated VLM latency in seconds (>= 0)")
    p.add_argument("--viewer", action="store_true", help="show the episodes live in viser (127.0.0.1:PORT)")
    p.add_argument("--port", type=int, default=8080, help="viewer TCP port on 127.0.0.1")
    p.add_argument("--json", default=None, help="also write every episode's metrics to this JSON file")


def register(subparsers, extra=()) -> argparse.ArgumentParser:
    """Add ``social`` (and ``social run``) to ``subparsers``; returns the ``social`` parser.

    ``extra``: callables that each receive the ``social`` sub-command set (``dest="social_command"``)
    and add their own sub-commands, e.g. ``social train`` / ``social eval``.
    """
    p = subparsers.add_parser("social", help="social navigation: DWA vs CoNVOI + DWA on simulated crowds",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
                              allow_abbrev=False)  # else `social train --seed` is read as an abbreviation of --seeds
    _add_run_args(p)
    p.set_defaults(func=run_command)
    sub = p.add_subparsers(dest="social_command", required=False)
    r = sub.add_parser("run", help="run the scenarios and print the tables (the default)")
    _add_run_args(r)
    r.set_defaults(func=run_command)
    for add in extra:
        add(sub)
    return p


def _scenarios(arg: str) -> list[str]:
    if arg == "all":
        return list(SCENARIOS)
    names = [s.strip() for s in arg.split(",") if s.strip()]
    bad = [n for n in names if n not in SCENARIOS]
    if bad or not names:
        raise ValueError(f"unknown scenario(s) {bad or arg!r}; choose from {', '.join(SCENARIOS)} or 'all'")
    return names


def _make_vlm(args):
    from .convoi.vlm import OpenAICompatibleVLM, ReplayVLM, RuleBasedVLM

    if args.vlm == "replay":
        if not args.vlm_record:
            raise ValueError("--vlm replay needs --vlm-record FILE")
        return ReplayVLM(args.vlm_record, mode="replay")
    if args.vlm == "openai":
        if not args.vlm_url:
            raise ValueError("--vlm openai needs --vlm-url (e.g. http://127.0.0.1:8000/v1)")
        inner = OpenAICompatibleVLM(args.vlm_url, args.vlm_model)
    else:
        inner = RuleBasedVLM()
    return ReplayVLM(args.vlm_record, inner, mode="record") if args.vlm_record else inner


def _viewer_observer(viewer):
    import numpy as np

    from .convoi.viewer import COLOURS

    def factory(scn, method, convoi=None):
        viewer.set_walls(scn.capsules)
        viewer.set_path("route", scn.global_path(), (170, 170, 170), z=0.01, thickness=0.02)
        trail = [np.asarray(scn.start[:2])]

        def observe(t, carry, out, ref):
            pose = np.asarray(carry.pose)
            trail.append(pose[:2])
            viewer.set_robot(pose)
            viewer.set_people(np.asarray(carry.peds.pos), np.asarray(carry.peds.active), np.asarray(out.detected),
                              scn.groups)
            viewer.set_rollout(np.asarray(out.best_traj))
            viewer.set_path(method, np.asarray(trail), COLOURS.get(method, (200, 200, 200)))
            if convoi is not None:
                viewer.set_reference(ref, pose[:2])
                if convoi.last_marked is not None and t % 10 == 0:
                    viewer.set_marked_image(convoi.last_marked)
            viewer.set_status(f"**{scn.name}** seed {scn.seed} · {method} · t = {t * scn.dt:.1f} s"
                              + (f" · context: {convoi.context_now}" if convoi is not None else ""))
            viewer.throttle()

        return observe

    return factory


def run_command(args: argparse.Namespace) -> int:
    """Handler of ``splatsearch social`` (and ``social run``): returns the exit status."""
    from rich.console import Console

    from .convoi import report
    from .convoi.pipeline import CoNVOIConfig

    if args.seeds < 1 or args.seed_offset < 0:
        raise ValueError("--seeds must be >= 1 and --seed-offset >= 0")
    if args.latency < 0:
        raise ValueError("--latency must be >= 0")
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    bad = [m for m in methods if m not in ("dwa", "convoi")]
    if bad or not methods:
        raise ValueError(f"--methods takes a comma list of dwa, convoi; got {args.methods!r}")
    names = _scenarios(args.scenario)
    seeds = list(range(args.seed_offset, args.seed_offset + args.seeds))
    console = Console()
    if not console.is_terminal:
        console.width = 160
    viewer = None
    factory = None
    if args.viewer:
        from .convoi.viewer import SocialViewer

        viewer = SocialViewer(port=args.port)
        console.print(f"viewer at {viewer.url} (local only); Ctrl-C stops")
        factory = _viewer_observer(viewer)
    try:
        with console.status("running episodes ...") as status:
            rows = report.evaluate(names, seeds, methods, vlm=_make_vlm(args),
                                   convoi_cfg=CoNVOIConfig(latency_s=args.latency), observer_factory=factory,
                                   progress=lambda s: status.update(f"running {s} ..."))
    finally:
        if viewer is not None:
            viewer.close()
    summary = report.summarise(rows)
    for t in report.tables(summary, len(seeds)):
        if t.row_count:
            console.print(t)
    if args.json:
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump({"episodes": [r.__dict__ for r in rows], "summary": summary}, f, indent=1, default=float)
        console.print(f"wrote {args.json}")
    return 0
