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


def _cmd_bench(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from splatsearch import bench
    from splatsearch.kernels import cpu_threads

    console = Console()
    if not console.is_terminal:  # piped or logged: do not squeeze the table into 80 columns
        console.width = 120
    scenes = []
    if args.scene in ("profile", "all"):
        scenes.append(("profile 112k 648x420", lambda: bench.profile_scene()))
    if args.scene in ("small", "all"):
        scenes.append(("random 10k 320x240", lambda: bench.random_scene()))
    table = Table(title=f"splatsearch rasterizer, CPU, {cpu_threads()} threads (median of {args.repeats})")
    for col in ("scene", "isect", "evals", "fwd ms", "fwd+bwd ms", "evals/s", "% peak"):
        table.add_column(col, justify="right", no_wrap=True)
    table.caption = "evals: exact Gaussian-pixel evaluations of one forward; peak: the 2-core CPU's ~5 G/s"
    with console.status("compiling kernels and timing...") as status:
        for name, make in scenes:
            status.update(f"timing {name} ...")
            r = bench.run_benchmark(make(), name, repeats=args.repeats)
            table.add_row(name, f"{r.n_isect:,}", f"{r.evals / 1e6:.1f} M", f"{1e3 * r.fwd_s:.1f}",
                          f"{1e3 * r.fwd_bwd_s:.1f}", f"{r.evals_per_s / 1e6:.0f} M", f"{100 * r.peak_fraction:.1f}")
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


def _cmd_map(args: argparse.Namespace) -> int:
    import json
    import os
    import time

    import numpy as np
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeRemainingColumn,
    )

    from splatsearch import datasets, io
    from splatsearch.mapper import Mapper, MapperConfig

    console = Console()
    with console.status("loading frames ..."):
        if args.tum:
            frames, K, W, H = datasets.load_tum(args.tum, max_frames=args.frames)
        else:
            frames, K, W, H, _ = datasets.sim_trajectory(args.seed, args.frames, args.width, args.height)
    every = max(2, args.holdout_every)
    held = [f for i, f in enumerate(frames) if i % every == every // 2] if args.holdout_every > 0 else []
    train = [f for i, f in enumerate(frames) if not (args.holdout_every > 0 and i % every == every // 2)]
    cfg = MapperConfig(iters=args.iters, stride=args.stride, isotropic=args.isotropic)
    mapper = Mapper(K, W, H, cfg)
    os.makedirs(args.out, exist_ok=True)
    times = []
    cols = (TextColumn("mapping"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[info]}"),
            TimeRemainingColumn())
    try:
        with Progress(*cols, console=console) as prog:
            task = prog.add_task("map", total=len(train), info="")
            for f in train:
                t0 = time.perf_counter()
                st = mapper.update(f.rgb, f.depth, f.viewmat)
                times.append(time.perf_counter() - t0)
                prog.update(task, advance=1, info=f"{st['n_gaussians']:,} Gaussians, loss {st['loss']:.4f}")
    except KeyboardInterrupt:
        console.print("[yellow]interrupted: saving the map built so far[/yellow]")
    n_ply = io.save_ply(mapper.map, os.path.join(args.out, "map.ply"))
    io.save_npz(mapper.map, os.path.join(args.out, "map.npz"), K=K, size=np.array([W, H]))
    with console.status("evaluating ..."):
        tr = mapper.evaluate(train[: len(times)])
        ho = mapper.evaluate(held) if held else None
    summary = {"frames_mapped": len(times), "gaussians": n_ply, "median_s_per_frame": float(np.median(times)) if times
               else None, "train": tr, "held_out": ho, "iters_per_frame": cfg.iters, "resolution": [W, H]}
    io.atomic_write_bytes(os.path.join(args.out, "summary.json"), json.dumps(summary, indent=1).encode())
    console.print(f"mapped {len(times)} frames, {n_ply:,} Gaussians, median {summary['median_s_per_frame']:.2f} s/frame")
    for label, ev in (("training views", tr), ("held-out views", ho)):
        if ev:
            console.print(f"{label}: PSNR {ev['psnr']:.2f} dB ({ev['psnr_valid']:.2f} dB where depth is valid), "
                          f"SSIM {ev['ssim']:.3f}, depth L1 {100 * ev['depth_l1']:.2f} cm")
    console.print(f"wrote {args.out}/map.ply, map.npz, summary.json")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from splatsearch.demo import DemoOptions, run_demo

    run_demo(DemoOptions(seed=args.seed, split=args.split, episode=args.episode, port=args.port,
                         viewer=not args.no_viewer, out=args.out, variant=args.variant, max_steps=args.max_steps,
                         hold=not args.exit_when_done))
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

    console = Console()
    if not console.is_terminal:
        console.width = 120
    variants = args.variants.split(",") if args.variants else None
    cols = (TextColumn("[bold]eval"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[info]}"),
            TimeElapsedColumn())
    with Progress(*cols, console=console) as prog:
        task = prog.add_task("eval", total=None, info="sampling episodes ...")

        def progress(r, done, total):
            prog.update(task, total=total, completed=done,
                        info=f"last: {r['variant']} ep {r['episode_id']} {'ok' if r['success'] else 'fail'} "
                             f"{r['steps']} steps {r['wall_time']:.0f} s")

        kw = {} if variants is None else {"variants": variants}
        overrides = {"appearance": False} if args.no_appearance else None
        _, summary = evaluate(args.split, args.episodes, args.seed, workers=args.workers, out=args.out,
                              max_steps=args.max_steps, progress=progress, resume=args.resume,
                              identical_furniture=args.identical_furniture,
                              agent_overrides=overrides, **kw)
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


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="splatsearch", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    from splatsearch._version import __version__

    p.add_argument("--version", action="version", version=f"splatsearch {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    b = sub.add_parser("bench", help="time the rasterizer on the benchmark scenes")
    b.add_argument("--scene", choices=["profile", "small", "all"], default="all")
    b.add_argument("--repeats", type=int, default=5, help="timed repetitions after warm-up (>= 1)")
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
        c.add_argument("--out", default=default_out)
        if name == "episodes":
            c.add_argument("--split", choices=["val", "val-hard"], default="val")
            c.add_argument("--n", type=int, default=10)
            c.add_argument("--episode-seed", type=int, default=0)
        c.set_defaults(func=_cmd_sim)

    m = sub.add_parser("map", help="build a Gaussian map from RGB-D frames and report PSNR / SSIM / depth L1")
    m.add_argument("--seed", type=int, default=0, help="simulator house seed (when --tum is not given)")
    m.add_argument("--tum", default=None, help="a TUM RGB-D folder (rgb/, depth/, rgb.txt, depth.txt, groundtruth.txt)")
    m.add_argument("--frames", type=int, default=100)
    m.add_argument("--width", type=int, default=320)
    m.add_argument("--height", type=int, default=240)
    m.add_argument("--iters", type=int, default=15, help="optimisation steps per frame")
    m.add_argument("--stride", type=int, default=3, help="densify every stride-th pixel")
    m.add_argument("--isotropic", action="store_true")
    m.add_argument("--holdout-every", type=int, default=8, help="hold out one frame in N for evaluation (0: none)")
    m.add_argument("--out", default="runs/map")
    m.set_defaults(func=_cmd_map)

    from splatsearch.agent import VARIANTS

    d = sub.add_parser("demo", help="a SplatSearch episode with the live viewer at http://127.0.0.1:PORT")
    d.add_argument("--seed", type=int, default=0, help="house seed (>= 0)")
    d.add_argument("--split", choices=["val", "val-hard"], default="val")
    d.add_argument("--episode", type=int, default=0, help="episode index in the house")
    d.add_argument("--port", type=port_number, default=8080,
                   help="viewer TCP port on 127.0.0.1, 0..65535; the next free one is taken if busy (default 8080)")
    d.add_argument("--no-viewer", action="store_true", help="headless: no viser server")
    d.add_argument("--exit-when-done", action="store_true", help="close the viewer when the episode ends")
    d.add_argument("--variant", choices=VARIANTS, default="splatsearch")
    d.add_argument("--max-steps", type=int, default=None, help="step cap (default: the episode's, 1000)")
    d.add_argument("--out", default="runs/demo")
    d.set_defaults(func=_cmd_demo)

    e = sub.add_parser("eval", help="SR / SPL of SplatSearch and its ablations")
    e.add_argument("--split", choices=["val", "val-hard"], default="val-hard")
    e.add_argument("--episodes", type=positive_int, default=50, help="episodes per variant, >= 1 (default 50)")
    e.add_argument("--seed", type=int, default=0, help="evaluation seed (selects the houses)")
    e.add_argument("--workers", type=int, default=1, help="parallel worker processes")
    e.add_argument("--variants", default=None,
                   help=f"comma-separated subset of {','.join(VARIANTS)} (default: the first five)")
    e.add_argument("--max-steps", type=int, default=None)
    e.add_argument("--resume", action="store_true",
                   help="keep the finished episodes in OUT/results.json and run only the missing ones")
    e.add_argument("--identical-furniture", action="store_true",
                   help="one model per furniture class in every house: same-class instances differ only in "
                        "their surroundings")
    e.add_argument("--no-appearance", action="store_true",
                   help="every variant identifies by feature matches alone (as the thesis), without the colour "
                        "cue, which cannot tell identical furniture apart")
    e.add_argument("--out", default="runs/eval")
    e.set_defaults(func=_cmd_eval)

    v = sub.add_parser("view", help="open a saved map in the viewer")
    v.add_argument("map", help="a .ply (INRIA layout) or .npz map")
    v.add_argument("--port", type=port_number, default=8080,
                   help="viewer TCP port on 127.0.0.1, 0..65535; the next free one is taken if busy (default 8080)")
    v.add_argument("--max-splats", type=positive_int, default=200_000,
                   help="initial splat budget drawn by the browser in RGB mode (default 200000)")
    v.add_argument("--max-z", type=float, default=None, help="hide Gaussians above this height (m), e.g. ceilings")
    v.set_defaults(func=_cmd_view)

    x = sub.add_parser("export", help="convert a map between .npz and .ply")
    x.add_argument("src")
    x.add_argument("dst")
    x.set_defaults(func=_cmd_export)

    from splatsearch.social.cli import register as register_social
    from splatsearch.social.olivia_cli import register_olivia

    register_social(sub, extra=[register_olivia])
    return p


def _one_line(e: BaseException) -> str:
    """The user-facing message of an exception: its text, or ``strerror: filename`` for an OSError
    raised by the OS (whose str() is ``[Errno 2] ...``)."""
    if isinstance(e, OSError) and e.strerror and e.filename:
        return f"{e.strerror}: {e.filename}"
    text = str(e).strip() or type(e).__name__
    return text.splitlines()[0] if "\n" in text else text


def positive_int(text: str) -> int:
    """argparse type of a count that must be >= 1."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {n}")
    return n


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
    args = build_parser().parse_args(argv)
    if getattr(args, "repeats", 1) < 1:
        build_parser().error("--repeats must be >= 1")
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


if __name__ == "__main__":
    sys.exit(main())
