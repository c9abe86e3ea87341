"""Command-line interface: ``splatsearch <command>``.

Commands:
    bench         time the rasterizer (forward and forward + backward) on the benchmark scenes.
    sim preview   top-down map and sample frames of a procedural house.
    sim episodes  sample instance-image-goal episodes of a house into a JSON file.
    sim export    write a procedural house as .glb.
    map           build a Gaussian map from a simulator trajectory or a TUM RGB-D folder.
    demo          one SplatSearch episode on a procedural house with the live viser viewer.
    eval          SR / SPL of SplatSearch and its ablations over many episodes.
    view          open a saved map (.ply or .npz) in the viser viewer.
    export        convert a map between .npz and .ply.
    social        social navigation: DWA and CoNVOI+DWA on the pedestrian scenarios (Tables I-II);
                  ``social train`` / ``social eval``: OLiVia-Nav.
"""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

from splatsearch.cli_types import positive_int

if TYPE_CHECKING:  # the mapper imports JAX; the CLI imports it only for the sub-commands that map
    from splatsearch.mapper import MapperConfig


def _cmd_bench(args: argparse.Namespace) -> int:
    import os

    from rich.console import Console
    from rich.table import Table

    from splatsearch import bench
    from splatsearch.kernels.config import resolve_threads

    if args.repeats < 1:
        raise SystemExit("--repeats must be >= 1")
    console = Console()
    if not console.is_terminal:  # piped or logged: do not squeeze the table into 80 columns
        console.width = 120
    makers = bench.scene_makers()
    names = list(makers) if args.scene == "all" else [{"small": "random10k"}.get(args.scene, args.scene)]
    threads = resolve_threads(args.threads, "cpu")
    table = Table(title=f"splatsearch rasterizer, CPU, {threads} threads, {args.composite or 'default'} kernel "
                        f"(median of {args.repeats})")
    for col in ("scene", "isect", "evals", "fwd ms", "fwd+bwd ms", "fwd cpu ms", "f+b cpu ms", "evals/s", "% peak"):
        table.add_column(col, justify="right", no_wrap=True)
    load0 = os.getloadavg()[0]
    with console.status("compiling kernels and timing...") as status:
        for name in names:
            status.update(f"building scene {name} ...")
            for label, scene in makers[name]():
                status.update(f"timing {label} ...")
                r = bench.run_benchmark(scene, label, repeats=args.repeats, composite=args.composite,
                                        threads=args.threads)
                table.add_row(label, f"{r.n_isect:,}", f"{r.evals / 1e6:.1f} M", f"{1e3 * r.fwd_s:.1f}",
                              f"{1e3 * r.fwd_bwd_s:.1f}", f"{1e3 * r.fwd_cpu_s:.1f}", f"{1e3 * r.fwd_bwd_cpu_s:.1f}",
                              f"{r.evals_per_s / 1e6:.0f} M",
                              f"{100 * r.peak_fraction:.1f}")
    table.caption = (f"evals: exact Gaussian-pixel evaluations of one per-pixel forward; evals/s and peak use the "
                     f"wall time; peak: the 2-core CPU's ~5 G/s; cpu ms: process CPU time, all threads; "
                     f"load average {load0:.1f} -> {os.getloadavg()[0]:.1f}")
    console.print(table)
    return 0


def _cmd_sim(args: argparse.Namespace) -> int:
    import time

    from rich.console import Console

    from splatsearch import sim

    console = Console()
    t0 = time.perf_counter()
    house = sim.make_house(args.seed, args.rooms, identical_furniture=args.identical_furniture)
    t_house = time.perf_counter() - t0
    if args.sim_command == "preview":
        with console.status("rendering preview ..."):
            paths = sim.preview.write_preview(house, args.out, seed=args.seed)
        console.print(f"house {args.seed}: {len(house.rooms)} rooms, {len(house.objects)} objects, "
                      f"{len(house.faces):,} triangles, built in {t_house * 1e3:.0f} ms")
        for p in paths:
            console.print(f"wrote {p}")
    elif args.sim_command == "episodes":
        env = sim.HouseEnv(house)
        with console.status(f"sampling {args.n} {args.split} episodes ..."):
            eps = sim.make_episodes(house, args.n, args.split, seed=args.episode_seed, env=env)
        sim.save_episodes(eps, args.out)
        console.print(f"wrote {len(eps)} episodes to {args.out}")
    elif args.sim_command == "export":
        sim.save_house(house, args.out)
        console.print(f"wrote {args.out}")
    return 0


#: ``splatsearch map --preset``: the optimisation budget and keyframing. ``quality`` is
#: ``benchmarks/slam_eval.py``'s real-sensor recipe (TUM fr1/xyz at 320x240, ground-truth poses:
#: 24.05 dB with each frame's exposure applied, ~7.7 CPU-s a frame; docs/mapping.md); every frame
#: is a keyframe there, which suits sequences of up to a few hundred frames.
MAP_PRESETS: dict[str, dict[str, int | None]] = {
    "fast": {"iters": 15, "first_iters": None, "stride": 3, "keyframe_every": 5, "refine": 0},
    "quality": {"iters": 30, "first_iters": 60, "stride": 2, "keyframe_every": 1, "refine": 500},
}


#: keyframe pose refinement's translation step (m) on simulator walks tracked with odometry
#: (``--odometry --pose-refine``): the recipe of ``benchmarks/slam_eval.py sim`` (docs/mapping.md).
SIM_ODOMETRY_POSE_LR_TRANS = 2e-5


def resolve_map_preset(args: argparse.Namespace) -> argparse.Namespace:
    """Fill the ``map`` flags left unset (None) from ``MAP_PRESETS[args.preset]``; flags given
    explicitly win. Returns ``args`` (changed in place; calling it twice changes nothing)."""
    for key, val in MAP_PRESETS[getattr(args, "preset", None) or "fast"].items():
        if getattr(args, key, None) is None:
            setattr(args, key, val)
    return args


def map_mapper_config(args: argparse.Namespace, real: bool) -> MapperConfig:
    """The :class:`~splatsearch.mapper.MapperConfig` of ``splatsearch map`` from its flags (and
    ``--preset``), before ``--mapper.FIELD`` overrides; ``real``: a dataset (``--data``), not a
    simulator walk."""
    from splatsearch.mapper import MapperConfig

    resolve_map_preset(args)

    mcfg = MapperConfig(iters=args.iters, stride=args.stride, isotropic=args.isotropic,
                        pixel_scale=args.pixel_scale if args.pixel_scale else float(args.stride if real else 1),
                        first_iters=args.first_iters, min_depth=args.depth_range[0], max_depth=args.depth_range[1],
                        fill_holes=real and not args.no_fill_holes, keyframe_every=args.keyframe_every,
                        initial_capacity=1 << 15 if real else 16384)
    if real:  # sensor depth is noisy: weigh it less and keep means steadier (docs/mapping.md)
        mcfg.lambda_g = 0.3
        mcfg.lr = dict(mcfg.lr, means=2e-4, colors=1e-2)
    # real cameras auto-expose (TUM's brightness drifts ~5 % over 10 frames): fit it unless told not to
    exposure = real if args.exposure is None else args.exposure
    mcfg.pose_refine, mcfg.pose_planar, mcfg.exposure = args.pose_refine, args.track_planar, exposure
    if args.pose_refine and getattr(args, "odometry", False):
        # with odometry the tracker's along-path prior holds the translation; the refinement's
        # unconstrained 2e-4 m steps pull keyframes back toward the map (results.md, stop 46)
        mcfg.pose_lr_trans = SIM_ODOMETRY_POSE_LR_TRANS
    return mcfg


def _cmd_map(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeRemainingColumn,
    )

    from splatsearch import datasets
    from splatsearch.map_job import MapJob, map_sequence
    from splatsearch.tracking_args import map_tracker_config

    # tracking options without --track are refused before any frame is loaded
    tcfg = map_tracker_config(args)
    console = Console()
    data = args.data or args.tum
    fmt = "tum" if (args.tum and not args.data and args.format == "auto") else args.format
    try:
        with console.status("loading frames ..."):
            if data:
                seq = datasets.load_sequence(data, fmt, max_frames=args.frames, downscale=args.downscale,
                                             require_poses=not args.track, undistort=not args.no_undistort,
                                             sync_depth=args.sync_depth)
            else:
                noise = (args.odometry_noise[0], args.odometry_noise[1]) if args.odometry else None
                seq = datasets.sim_walk(args.seed, args.frames or 100, args.width, args.height, odometry_noise=noise)
    except (FileNotFoundError, NotADirectoryError, PermissionError) as e:
        print(f"splatsearch: error: {e}", file=sys.stderr)
        return 2
    if args.sync_depth and args.track:
        raise ValueError("--sync-depth uses ground-truth motion, which --track must not see")
    if args.odometry and data:
        raise ValueError("--odometry is for simulator walks; datasets carry no odometry")
    real = data is not None
    mcfg = map_mapper_config(args, real)
    from splatsearch.cli_config import apply_overrides, config_overrides

    mcfg = apply_overrides(mcfg, config_overrides(args, "mapper"))  # --mapper.FIELD wins over the flags above
    job = MapJob(mcfg, tcfg, track=args.track, use_odometry=args.odometry, holdout_every=args.holdout_every,
                 refine=args.refine, gt_prior=args.track_from_gt)
    for note in seq.notes:
        console.print(f"[dim]{seq.format}: {note}[/dim]")
    cols = (TextColumn("tracking+mapping" if args.track else "mapping"), BarColumn(), MofNCompleteColumn(),
            TextColumn("{task.fields[info]}"), TimeRemainingColumn())
    with Progress(*cols, console=console) as prog:
        task = prog.add_task("map", total=None, info="")

        def progress(r, done, total):
            st = r.stats
            info = (f"track {r.t_track:.2f} s, map {r.t_map:.2f} s, {st.get('n_gaussians', 0):,} Gaussians"
                    if r.mapped else f"[yellow]frame {r.index}: {r.status}[/yellow]")
            prog.update(task, total=total, completed=done, info=info)
            if not r.mapped:
                prog.console.print(f"[yellow]frame {r.index}: {r.status.replace('_', ' ')}[/yellow]")

        _, summary = map_sequence(seq, job, args.out, progress)
    if summary["interrupted"]:
        console.print("[yellow]interrupted: saved the map built so far[/yellow]")
    tm = summary["timing"]
    line = (f"mapped {summary['frames_mapped']} of {summary['frames_processed']} frames, "
            f"{summary['gaussians']:,} Gaussians")
    if tm["median_map_s"] is not None:
        line += f"; median per frame: mapping {tm['median_map_s']:.2f} s"
    if tm["median_track_s"] is not None:
        line += f", tracking {tm['median_track_s']:.2f} s"
    console.print(line)
    for label, key in (("training views", "train"), ("training views at GT poses", "train_at_gt_pose"),
                       ("keyframes, own exposure applied", "train_keyframes_exposure"), ("held-out views", "held_out"),
                       ("held-out views at poses tracked in the map", "held_out_tracked")):
        ev = summary.get(key)
        if ev:
            console.print(f"{label}: PSNR {ev['psnr']:.2f} dB ({ev['psnr_valid']:.2f} dB where depth is valid), "
                          f"SSIM {ev['ssim']:.3f}, depth L1 {100 * ev['depth_l1']:.2f} cm")
    if "ate" in summary:
        a = summary["ate"]
        console.print(f"ATE RMSE {100 * a['rmse']:.2f} cm (mean {100 * a['mean']:.2f}, max {100 * a['max']:.2f} cm, "
                      f"{a['n']} poses)")
    if "ate_odometry" in summary:
        console.print(f"odometry alone: ATE RMSE {100 * summary['ate_odometry']['rmse']:.2f} cm")
    console.print(f"wrote {args.out}/map.ply, map.npz, trajectory.txt, summary.json")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from splatsearch.demo import DemoOptions, run_demo

    from splatsearch.cli_config import config_overrides

    run_demo(DemoOptions(seed=args.seed, split=args.split, episode=args.episode, port=args.port,
                         viewer=not args.no_viewer, out=args.out, variant=args.variant, max_steps=args.max_steps,
                         hold=not args.exit_when_done,
                         agent_overrides={**config_overrides(args, "agent"), **_plugin_overrides(args)}))
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
    )

    from splatsearch.evaluation import eval_title, evaluate, markdown_table
    from splatsearch.parallel import executor_from_args

    console = Console()
    if not console.is_terminal:
        console.width = 120
    variants = args.variants.split(",") if args.variants else None
    cols = (TextColumn("[bold]eval"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[counts]}"),
            TextColumn("{task.fields[info]}"), TimeElapsedColumn())
    last = {"info": ""}
    with Progress(*cols, console=console) as prog:
        task = prog.add_task("eval", total=None, counts="", info="sampling episodes ...")

        def progress(r, c):
            if r is not None:
                last["info"] = (f"last: {r['variant']} ep {r['episode_id']} "
                                f"{'error' if 'error' in r else 'ok' if r['success'] else 'fail'} "
                                f"{r['steps']} steps {r['wall_time']:.0f} s")
            prog.update(task, total=c.total, completed=c.done, info=last["info"],
                        counts=f"running {c.running} · failed {c.failed}" + (f" · retried {c.retried}" if c.retried
                                                                            else ""))

        kw = {} if variants is None else {"variants": variants}
        import json

        from splatsearch.cli_config import config_overrides

        # JSON-normal (tuples as lists) so that a --resume compares equal with results.json
        overrides = json.loads(json.dumps({**config_overrides(args, "agent"), **_plugin_overrides(args),
                                           **({"colour_cue": False} if args.no_colour_cue else {})})) or None
        executor = executor_from_args(args)
        try:
            _, summary = evaluate(args.split, args.episodes, args.seed, out=args.out, max_steps=args.max_steps,
                                  progress=progress, resume=args.resume, identical_furniture=args.identical_furniture,
                                  agent_overrides=overrides, executor=executor, **kw)
        except KeyboardInterrupt:
            prog.stop()
            console.print(f"[yellow]interrupted: every finished episode is in {args.out}/results.json; "
                          "run again with --resume to finish[/yellow]")
            raise
        finally:
            executor.close()
    console.print(markdown_table(summary, eval_title(args.split, args.episodes, args.seed, args.identical_furniture,
                                                     overrides)))
    console.print(f"wrote {args.out}/results.json, summary.json, summary.md")
    return 0


def _load_map(path: str):
    import os

    from splatsearch import io

    if not os.path.exists(path):
        raise FileNotFoundError(f"no such map file: {path}")
    if os.path.isdir(path):
        raise IsADirectoryError(f"expected a .ply or .npz map file, got the folder {path}")
    if path.endswith(".ply"):
        return io.load_ply(path)
    if path.endswith(".npz"):
        return io.load_npz(path)[0]
    raise ValueError(f"expected a .ply or .npz map, got {path!r}")


def _cmd_view(args: argparse.Namespace) -> int:
    import time

    from splatsearch.map_viewer import MapViewer

    gmap = _load_map(args.map)
    viewer = MapViewer(gmap, port=args.port, max_splats=args.max_splats, max_z=args.max_z)
    print(f"showing {viewer.n_shown:,} of {viewer.n_total:,} Gaussians at {viewer.url}; press Ctrl-C to exit")
    try:
        while True:
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.close()
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    from splatsearch import io

    gmap = _load_map(args.src)
    if args.dst.endswith(".ply"):
        n = io.save_ply(gmap, args.dst)
    elif args.dst.endswith(".npz"):
        io.save_npz(gmap, args.dst)
        n = gmap.n_active
    else:
        raise ValueError(f"the output must end in .ply or .npz, got {args.dst!r}")
    print(f"wrote {n:,} Gaussians to {args.dst}")
    return 0


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Keeps descriptions as written and ends every option's help with its default, unless the
    help already names it ("default: ..."); on/off flags read "(default: off)"."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if not action.option_strings or "default" in text or action.default is argparse.SUPPRESS:
            return text
        if isinstance(action, argparse._StoreTrueAction):
            return f"{text} (default: off)"
        if action.default is None:
            return f"{text} (default: none)"
        return f"{text} (default: %(default)s)"


def _use_formatter(parser: argparse.ArgumentParser) -> None:
    """Give ``parser`` and all its sub-command parsers :class:`HelpFormatter`."""
    parser.formatter_class = HelpFormatter
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            for sp in a.choices.values():
                _use_formatter(sp)


#: sub-commands that take every field of config dataclasses as ``--PREFIX.FIELD`` (see
#: :mod:`splatsearch.cli_config`): a list per command of (prefix, "module:Class", fields left to
#: the command's own flags, "module:DICT" of per-field help or None: the class docstring's).
#: ``TrackerConfig.planar`` stays with ``--track-planar``, which also sets the mapper's planar
#: pose refinement.
CONFIG_FLAGS: dict[str, list[tuple[str, str, tuple[str, ...], str | None]]] = {
    "map": [("mapper", "splatsearch.mapper:MapperConfig", (), None),
            ("tracker", "splatsearch.slam:TrackerConfig", ("planar",), "splatsearch.tracking_args:TRACKER_FIELD_HELP")],
    "demo": [("agent", "splatsearch.agent.config:AgentConfig", ("variant",), None)],
    "eval": [("agent", "splatsearch.agent.config:AgentConfig", ("variant",), None)],
}


def _load(path: str):
    """The object named by ``"module:NAME"``."""
    import importlib

    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)


def _add_plugin_flags(parser: argparse.ArgumentParser) -> None:
    """``--detector`` / ``--matcher`` plug-in spec flags (:mod:`splatsearch.plugins`)."""
    from splatsearch.plugins import DETECTOR_HELP, MATCHER_HELP

    parser.add_argument("--detector", default=None, metavar="SPEC",
                        help=DETECTOR_HELP.replace("; default)", ")") + " (default: sim)")
    parser.add_argument("--matcher", default=None, metavar="SPEC",
                        help=MATCHER_HELP.replace("; default)", ")") + " (default: sift)")


def _plugin_overrides(args: argparse.Namespace) -> dict:
    """AgentConfig overrides of ``--detector`` / ``--matcher``, checked here (unknown kind, missing
    file) before any episode or worker starts."""
    from splatsearch.plugins import make_detector, make_matcher

    out = {}
    if args.detector is not None:
        make_detector(args.detector)
        out["detector"] = args.detector
    if args.matcher is not None:
        make_matcher(args.matcher)
        out["matcher"] = args.matcher
    return out


def _command_of(argv: list[str]) -> str | None:
    return next((a for a in argv if not a.startswith("-")), None)


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The ``splatsearch`` parser. Building it imports neither JAX nor Warp: every command's heavy
    modules are imported inside its handler. When ``argv`` names ``map``, ``demo`` or ``eval``,
    that command also gets a flag per config field (:data:`CONFIG_FLAGS`; ``map``: ``--mapper.FIELD``
    and ``--tracker.FIELD``), which loads its config classes (and so JAX)."""
    p = argparse.ArgumentParser(prog="splatsearch", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    from splatsearch._version import __version__

    p.add_argument("--version", action="version", version=f"splatsearch {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    b = sub.add_parser("bench", help="time the rasterizer on the benchmark scenes")
    b.add_argument("--scene", choices=["profile", "heavy", "house", "random10k", "small", "all"], default="all",
                   help="(a) profile: 112k Gaussians in a room at 648x420; (b) heavy: the same room with scales "
                        "U[5e-4, 0.1] m; (c) house: the mapper's map of simulator house 0 at 320x240 and 640x480; "
                        "(d) random10k (alias small): 10k random Gaussians at 320x240; all: every one (default: all)")
    b.add_argument("--repeats", type=int, default=5, help="timed repetitions after warm-up, >= 1 (default: 5)")
    b.add_argument("--threads", type=int, default=None,
                   help="CPU worker threads, >= 1 (default: the usable cores, or $SPLATSEARCH_THREADS)")
    b.add_argument("--composite", choices=["tile", "pixel"], default=None,
                   help="compositing kernel (default: tile on the CPU, or $SPLATSEARCH_COMPOSITE)")
    b.set_defaults(func=_cmd_bench)

    s = sub.add_parser("sim", help="procedural houses and IIN episodes")
    ssub = s.add_subparsers(dest="sim_command", required=True)
    for name, help_, default_out in (("preview", "top-down map + sample frames (PNG)", "runs/preview"),
                                     ("episodes", "sample episodes into a JSON file", "runs/episodes.json"),
                                     ("export", "write the house as .glb", "runs/house.glb")):
        c = ssub.add_parser(name, help=help_)
        c.add_argument("--seed", type=int, default=0, help="house seed (>= 0)")
        c.add_argument("--rooms", type=int, default=None, help="number of rooms, 3..8 (default: from the seed)")
        c.add_argument("--identical-furniture", action="store_true", help="one model per furniture class")
        c.add_argument("--out", default=default_out, help="output path")
        if name == "episodes":
            c.add_argument("--split", choices=["val", "val-hard"], default="val",
                           help="val: goal image from a navigable viewpoint; val-hard: from a sphere around the object")
            c.add_argument("--n", type=int, default=10, help="number of episodes")
            c.add_argument("--episode-seed", type=int, default=0, help="seed of the episode sampler (>= 0)")
        c.set_defaults(func=_cmd_sim)

    m = sub.add_parser("map", help="build a Gaussian map from RGB-D frames (a dataset or a simulator walk), "
                                   "optionally tracking the camera; reports PSNR / SSIM / depth L1 and ATE")
    m.add_argument("--data", default=None, metavar="PATH",
                   help="an RGB-D dataset folder (default: a simulator walk through house --seed)")
    m.add_argument("--format", default="auto", choices=["auto", "tum", "replica", "scannet", "7scenes", "folder"],
                   help="layout of --data (default: auto-detect)")
    m.add_argument("--tum", default=None, metavar="PATH", help="alias of --data PATH for a TUM RGB-D folder")
    m.add_argument("--track", action="store_true",
                   help="estimate camera poses by tracking against the map (first pose: ground truth if known, "
                        "else identity); ground-truth poses are then used only for ATE")
    m.add_argument("--odometry", action="store_true",
                   help="simulator only: use the walk's noisy odometry as the tracking prior (with --track)")
    m.add_argument("--odometry-noise", type=float, nargs=2, default=(0.05, 0.01), metavar=("TRANS", "ROT"),
                   help="simulated odometry noise: fraction of distance moved, rad per frame (default 0.05 0.01)")
    m.add_argument("--seed", type=int, default=0, help="simulator house seed (without --data; default 0)")
    m.add_argument("--frames", type=int, default=None,
                   help="use at most this many frames (default: all of --data, 100 for the simulator)")
    m.add_argument("--downscale", type=int, default=1,
                   help="divide dataset image size by this integer (2: 640x480 -> 320x240; default 1)")
    m.add_argument("--no-undistort", action="store_true", help="keep the lens distortion of TUM fr1/fr2 frames")
    m.add_argument("--sync-depth", action="store_true",
                   help="TUM with ground-truth poses: move each depth image to its colour image's timestamp "
                        "(~15 ms later) with the ground-truth motion; not with --track")
    m.add_argument("--width", type=int, default=320, help="simulator image width in pixels (default 320)")
    m.add_argument("--height", type=int, default=240, help="simulator image height in pixels (default 240)")
    m.add_argument("--preset", default="fast", choices=sorted(MAP_PRESETS),
                   help="optimisation budget: 'fast' (15 steps a frame, densify every 3rd pixel, a keyframe "
                        "every 5 frames, no final refinement) or 'quality' (the real-sensor benchmark's recipe: "
                        "30 steps a frame, 60 for the first, every 2nd pixel, every frame a keyframe, 500 "
                        "refinement steps; about 1.6x the CPU time on 10 TUM frames); the flags below win "
                        "(default: fast)")
    m.add_argument("--iters", type=positive_int, default=None,
                   help="mapping Adam steps per frame (default: 15; --preset quality: 30)")
    m.add_argument("--first-iters", type=positive_int, default=None,
                   help="mapping steps for the first frame (default: --iters; --preset quality: 60)")
    m.add_argument("--refine", type=int, default=None, help="mapping steps over the keyframes after the last frame "
                                                            "(default: 0; --preset quality: 500)")
    m.add_argument("--keyframe-every", type=positive_int, default=None,
                   help="every N-th mapped frame becomes a keyframe (default: 5; --preset quality: 1; "
                        "1 for short sequences)")
    from splatsearch.tracking_args import add_track_args

    add_track_args(m)
    m.add_argument("--pose-refine", action="store_true",
                   help="with --track: refine the tracked keyframe poses jointly with the map during mapping "
                        "(a local bundle adjustment through the renderer; default: off; with --odometry its translation "
                        "step is 2e-5 m unless --mapper.pose_lr_trans says otherwise)")
    m.add_argument("--exposure", action=argparse.BooleanOptionalAction, default=None,
                   help="fit an affine colour (gain, bias) per frame, for cameras with auto-exposure; "
                        "summary.json adds the keyframes' PSNR with it applied (default: on for --data, "
                        "off for the simulator)")
    m.add_argument("--stride", type=positive_int, default=None,
                   help="densify every stride-th pixel (default: 3; --preset quality: 2)")
    m.add_argument("--pixel-scale", type=float, default=None,
                   help="size of new Gaussians in pixels (default: --stride for datasets, 1 for the simulator)")
    m.add_argument("--depth-range", type=float, nargs=2, default=(0.0, float("inf")), metavar=("MIN", "MAX"),
                   help="trust depth only within MIN..MAX metres (default: all)")
    m.add_argument("--no-fill-holes", action="store_true",
                   help="datasets: do not densify pixels without depth at the neighbouring background depth")
    m.add_argument("--isotropic", action="store_true", help="spherical Gaussians (one scale each)")
    m.add_argument("--holdout-every", type=int, default=8,
                   help="hold out one frame in N for evaluation (0: none; default 8)")
    m.add_argument("--out", default="runs/map", help="output folder (default runs/map)")
    m.set_defaults(func=_cmd_map)

    from splatsearch.agent import VARIANTS

    d = sub.add_parser("demo", help="a SplatSearch episode with the live viewer at http://127.0.0.1:PORT")
    d.add_argument("--seed", type=int, default=0, help="house seed (>= 0)")
    d.add_argument("--split", choices=["val", "val-hard"], default="val", help="episode split")
    d.add_argument("--episode", type=int, default=0, help="episode index in the house")
    d.add_argument("--port", type=port_number, default=8080,
                   help="viewer TCP port on 127.0.0.1, 0..65535; a busy port moves on to the next free one")
    d.add_argument("--no-viewer", action="store_true", help="headless: no viser server")
    d.add_argument("--exit-when-done", action="store_true", help="close the viewer when the episode ends")
    from splatsearch.agent.variants import VARIANT_ALIASES

    d.add_argument("--variant", choices=VARIANTS + tuple(VARIANT_ALIASES), default="splatsearch",
                   help="the full system or one of its ablations (no_inpaint is an alias of no_vcicn)")
    d.add_argument("--max-steps", type=int, default=None, help="step cap (default: the episode's, 1000)")
    d.add_argument("--out", default="runs/demo", help="output directory (map.ply, trajectory and summary)")
    _add_plugin_flags(d)
    d.set_defaults(func=_cmd_demo)

    e = sub.add_parser("eval", help="SR / SPL of SplatSearch and its ablations")
    e.add_argument("--split", choices=["val", "val-hard"], default="val-hard", help="episode split")
    e.add_argument("--episodes", type=positive_int, default=50,
                   help="episodes (5 per house), each run with every variant, >= 1")
    e.add_argument("--seed", type=int, default=0, help="evaluation seed (selects the houses)")
    from splatsearch.parallel import add_executor_args

    add_executor_args(e, default_workers=None)
    e.add_argument("--variants", default=None,
                   help=f"comma-separated subset of {','.join(VARIANTS)} (no_inpaint: alias of no_vcicn; "
                        f"default: all {len(VARIANTS)})")
    e.add_argument("--max-steps", type=int, default=None,
                   help="step cap per episode, in agent actions (default: the episode's, 1000)")
    _add_plugin_flags(e)
    e.add_argument("--resume", action="store_true",
                   help="keep the finished episodes in OUT/results.json and run only the missing ones")
    e.add_argument("--identical-furniture", action="store_true",
                   help="one model per furniture class in every house: same-class instances differ only in "
                        "their surroundings")
    e.add_argument("--no-colour-cue", "--no-appearance", dest="no_colour_cue", action="store_true",
                   help="every variant identifies by feature matches alone (as the thesis), without the colour "
                        "cue, which cannot tell identical furniture apart (default: off)")
    e.add_argument("--out", default="runs/eval",
                   help="output folder: results.json (after every episode), summary.json, summary.md")
    e.set_defaults(func=_cmd_eval)

    from splatsearch.vcicn.cli import add_parser as _add_vcicn_parser

    _add_vcicn_parser(sub)

    v = sub.add_parser("view", help="open a saved map in the viewer")
    v.add_argument("map", help="a .ply (INRIA layout) or .npz map")
    v.add_argument("--port", type=port_number, default=8080,
                   help="viewer TCP port on 127.0.0.1, 0..65535; a busy port moves on to the next free one")
    v.add_argument("--max-splats", type=positive_int, default=200_000,
                   help="initial splat budget drawn by the browser in RGB mode")
    v.add_argument("--max-z", type=float, default=None, help="hide Gaussians above this height (m), e.g. ceilings")
    v.set_defaults(func=_cmd_view)

    x = sub.add_parser("export", help="convert a map between .npz and .ply")
    x.add_argument("src", help="the map to read (.ply or .npz)")
    x.add_argument("dst", help="the file to write (.ply or .npz)")
    x.set_defaults(func=_cmd_export)

    from splatsearch.social.cli import register as register_social
    from splatsearch.social.olivia.cli import register_olivia

    register_social(sub, extra=[register_olivia])
    command = _command_of(list(argv or []))
    if command in CONFIG_FLAGS:
        from splatsearch.cli_config import add_config_flags

        for prefix, path, skip, helps in CONFIG_FLAGS[command]:
            add_config_flags(sub.choices[command], _load(path), prefix, skip=skip,
                             helps=_load(helps) if helps else None)
    _use_formatter(p)
    return p


def _one_line(e: BaseException) -> str:
    """The user-facing message of an exception: its text, or ``strerror: filename`` for an OSError
    raised by the OS (whose str() is ``[Errno 2] ...``)."""
    if isinstance(e, OSError) and e.strerror and e.filename:
        return f"{e.strerror}: {e.filename}"
    text = str(e).strip() or type(e).__name__
    return text.splitlines()[0] if "\n" in text else text


def port_number(text: str) -> int:
    """argparse type of a TCP port: an integer in 0..65535 (0 lets the OS choose)."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a port number: {text!r}") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"port must be in 0..65535, got {port}")
    return port


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser(argv).parse_args(argv)
    if getattr(args, "repeats", 1) < 1:
        build_parser().error("--repeats must be >= 1")
    import logging

    from rich.console import Console
    from rich.logging import RichHandler

    # the library logs through `logging` (never print); the CLI shows INFO and up on stderr
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s", datefmt="[%X]",
                        handlers=[RichHandler(show_path=False, console=Console(stderr=True))])
    for noisy in ("jax", "absl", "httpx", "httpcore", "websockets", "asyncio"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    from splatsearch.compile_cache import enable_compile_cache

    enable_compile_cache()
    try:
        return args.func(args)
    except (ValueError, OSError) as e:
        # ordinary mistakes (a bad path, a busy port, a malformed file) get one line, not a traceback
        print(f"splatsearch: error: {_one_line(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as e:
        # a failed input check inside a jitted rasterizer call arrives wrapped by XLA
        if type(e).__name__ == "JaxRuntimeError" and "InputValueError: " in str(e):
            print(f"splatsearch: error: {str(e).split('InputValueError: ', 1)[1].splitlines()[0]}", file=sys.stderr)
            return 2
        raise


if __name__ == "__main__":
    sys.exit(main())
