"""Command-line interface: ``splatsearch <command>``.

Commands:
    bench   time the rasterizer (forward and forward + backward) on the benchmark scenes.
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


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="splatsearch", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    b = sub.add_parser("bench", help="time the rasterizer on the benchmark scenes")
    b.add_argument("--scene", choices=["profile", "small", "all"], default="all")
    b.add_argument("--repeats", type=int, default=5, help="timed repetitions after warm-up (>= 1)")
    b.set_defaults(func=_cmd_bench)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if getattr(args, "repeats", 1) < 1:
        build_parser().error("--repeats must be >= 1")
    try:
        return args.func(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
