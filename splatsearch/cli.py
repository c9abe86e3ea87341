"""Command-line interface: ``splatsearch <command>``.

Commands:
    bench         time the rasterizer (forward and forward + backward) on the benchmark scenes.
    sim preview   top-down map and sample frames of a procedural house.
    sim episodes  sample instance-image-goal episodes of a house into a JSON file.
    sim export    write a procedural house as .glb.
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
    scenes = []
    if args.scene in ("profile", "all"):
        scenes.append(("profile 111,785 @ 648x420", lambda: bench.profile_scene()))
    if args.scene in ("small", "all"):
        scenes.append(("random 10k @ 320x240", lambda: bench.random_scene()))
    table = Table(title=f"splatsearch rasterizer, CPU, {cpu_threads()} threads (median of {args.repeats})")
    for col in ("scene", "intersections", "Gaussian-pixel evals", "forward ms", "fwd+bwd ms", "evals/s",
                "of 5 G/s peak"):
        table.add_column(col, justify="right")
    with console.status("compiling kernels and timing...") as status:
        for name, make in scenes:
            status.update(f"timing {name} ...")
            r = bench.run_benchmark(make(), name, repeats=args.repeats)
            table.add_row(name, f"{r.n_isect:,}", f"{r.evals:,}", f"{1e3 * r.fwd_s:.1f}", f"{1e3 * r.fwd_bwd_s:.1f}",
                          f"{r.evals_per_s / 1e6:.0f} M", f"{100 * r.peak_fraction:.1f} %")
    console.print(table)
    return 0


def _cmd_sim(args: argparse.Namespace) -> int:
    import time

    from rich.console import Console

    from splatsearch import sim

    console = Console()
    t0 = time.perf_counter()
    house = sim.make_house(args.seed, args.rooms)
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


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="splatsearch", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
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
        c.add_argument("--out", default=default_out)
        if name == "episodes":
            c.add_argument("--split", choices=["val", "val-hard"], default="val")
            c.add_argument("--n", type=int, default=10)
            c.add_argument("--episode-seed", type=int, default=0)
        c.set_defaults(func=_cmd_sim)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if getattr(args, "repeats", 1) < 1:
        build_parser().error("--repeats must be >= 1")
    try:
        return args.func(args)
    except ValueError as e:
        print(f"splatsearch: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
