"""``splatsearch demo``: one SplatSearch episode on a procedural house, watched live in viser.

The run folder gets ``map.ply`` (INRIA layout), ``trajectory.json`` (true poses), ``episode.json``
and ``summary.json``; all written atomically, and also on Ctrl-C with what was done so far.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass

import numpy as np

from splatsearch import io
from splatsearch.cli_config import apply_overrides
from splatsearch.agent import AgentConfig, SplatSearchAgent, StepInfo


@dataclass
class DemoOptions:
    """Options of :func:`run_demo` (the CLI flags)."""

    seed: int = 0
    split: str = "val"
    episode: int = 0
    port: int = 8080
    viewer: bool = True
    out: str = "runs/demo"
    variant: str = "splatsearch"
    max_steps: int | None = None
    hold: bool = True  # keep the viewer up after the episode until Ctrl-C
    agent_overrides: dict | None = None  # AgentConfig fields to change (nested dicts for nested configs)


class ViewerBridge:
    """Feeds a :class:`~splatsearch.viewer.SearchViewer` from the agent after every step.

    Cheap layers (camera, trajectory, path, frontiers, objects) are sent every step; the map
    after every mapped frame and the grid planes every ``grid_every`` steps.
    """

    def __init__(self, viewer, goal_rgb: np.ndarray, grid_every: int = 5):
        self.v = viewer
        self.grid_every = grid_every
        self.traj: list[np.ndarray] = []
        self.nvsm_seen = 0
        self.steps = 0
        self.seconds = 0.0
        viewer.set_goal(goal_rgb)

    def update(self, agent: SplatSearchAgent, obs, info: StepInfo) -> None:
        t0 = time.perf_counter()
        v = self.v
        self.traj.append(np.asarray(obs.gt_pose[:2]))
        v.set_camera(obs.viewmat, agent.K, obs.frame.rgb)
        v.set_trajectory(np.asarray(self.traj))
        v.set_path(agent.path_xy)
        fr = agent.last_decision.frontiers if agent.last_decision is not None else []
        chosen = None
        if agent.last_decision is not None and agent.last_decision.target is not None:
            chosen = next((i for i, f in enumerate(fr) if f is agent.last_decision.target), None)
        v.set_frontiers(np.array([f.waypoint_xy for f in fr]).reshape(-1, 2), chosen)
        v.set_objects([{"centroid": e.centroid, "extent": (e.bbox_max - e.bbox_min) if e.bbox_min is not None
                        else (0.4, 0.4, 0.4), "label": e.label, "score": max(e.e_max, 0), "matched": agent.is_goal(e)}
                       for e in agent.db])
        if "map" in info.timings and agent.mapper.map.n_active:
            v.set_gaussian_map(agent.mapper.map)
        if self.steps % self.grid_every == 0:
            occ = agent.explorer.occupancy
            v.set_occupancy(occ.state, occ.spec.origin_xy, occ.spec.cell_size)
            vm = agent.explorer.value_map
            v.set_value_map(np.asarray(vm.value), np.asarray(vm.confidence), vm.spec.origin_xy, vm.spec.cell_size)
        if agent.nvsm_runs != self.nvsm_seen and agent.last_views is not None:
            self.nvsm_seen = agent.nvsm_runs
            lv = agent.last_views
            v.set_novel_views(lv.viewmats, agent.K, lv.rendered, lv.inpainted, lv.best)
        v.add_match_score(obs.step + 1, info.best_score)
        v.set_status(f"**step {obs.step + 1}** · {info.status} · frontiers {info.n_frontiers} · objects "
                     f"{info.n_objects} · best match {info.best_score:.0f}")
        self.steps += 1
        self.seconds += time.perf_counter() - t0
        v.throttle()


def run_demo(opts: DemoOptions, console=None) -> dict:
    """Run the demo episode; returns the summary dict (also saved to ``out/summary.json``)."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from splatsearch import sim
    from splatsearch.episode import run_episode

    if console is None:
        console = Console()
        if not console.is_terminal:  # piped or logged: room for the progress line
            console.width = 120
    if opts.split not in sim.SPLITS:
        raise ValueError(f"split must be one of {sim.SPLITS}, got {opts.split!r}")
    if opts.seed < 0 or opts.episode < 0:
        raise ValueError("seed and episode must be >= 0")
    os.makedirs(opts.out, exist_ok=True)
    t_start = time.perf_counter()
    with console.status("building the house and sampling the episode ..."):
        house = sim.make_house(opts.seed)
        env = sim.HouseEnv(house)
        ep = sim.make_episodes(house, opts.episode + 1, opts.split, seed=opts.seed, env=env)[opts.episode]
        goal = sim.goal_image(env, ep).rgb
    io.atomic_write_bytes(os.path.join(opts.out, "episode.json"), json.dumps(ep.to_json(), indent=1).encode())
    viewer = bridge = None
    if opts.viewer:
        from splatsearch.viewer import SearchViewer

        viewer = SearchViewer(port=opts.port)
        bridge = ViewerBridge(viewer, goal)
        console.print(f"[bold green]viewer:[/bold green] open {viewer.url} in a browser")
    console.print(f"house {opts.seed}, episode {ep.episode_id} ({opts.split}): find the {ep.goal_class} "
                  f"shown in {opts.out}/goal.png; d* = {ep.d_star:.1f} m")
    import cv2

    ok, png = cv2.imencode(".png", (np.clip(goal, 0, 1)[..., ::-1] * 255).astype(np.uint8))
    io.atomic_write_bytes(os.path.join(opts.out, "goal.png"), png.tobytes())
    state: dict = {"agent": None, "traj": [], "info": None}
    cap = opts.max_steps or ep.max_steps
    cols = (TextColumn("[bold]search"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[info]}"),
            TimeElapsedColumn())
    result = None
    interrupted = False
    try:
        with Progress(*cols, console=console) as prog:
            task = prog.add_task("search", total=cap, info="")

            def on_step(agent, obs, info):
                state["agent"], state["info"] = agent, info
                state["traj"].append(obs.gt_pose.tolist())
                prog.update(task, completed=obs.step + 1,
                            info=f"{info.status:<16} frontiers {info.n_frontiers:>2}  objects {info.n_objects}  "
                                 f"best match {info.best_score:>3.0f}  {time.perf_counter() - t_start:5.0f} s")
                if bridge is not None:
                    bridge.update(agent, obs, info)

            config = apply_overrides(AgentConfig(variant=opts.variant), opts.agent_overrides or {})
            result = run_episode(ep, config, env=env, on_step=on_step,
                                 max_steps=opts.max_steps)
    except KeyboardInterrupt:
        interrupted = True
        console.print("[yellow]interrupted: saving what was done so far[/yellow]")
    summary = _save_run(opts.out, ep, opts.variant, state, result, interrupted, time.perf_counter() - t_start, bridge)
    if result is not None:
        console.print(f"[bold]{'SUCCESS' if result.success else 'FAILURE'}[/bold]: SPL {result.spl:.3f}, "
                      f"{result.steps} steps, {result.path_length:.1f} m (d* {result.d_star:.1f} m), "
                      f"{summary['wall_time_s']:.0f} s, final status {result.status}")
    if bridge is not None and bridge.steps:
        console.print(f"viewer updates: {1e3 * bridge.seconds / bridge.steps:.1f} ms per step")
    console.print(f"wrote {opts.out}/map.ply, trajectory.json, episode.json, summary.json")
    if viewer is not None:
        if opts.hold and not interrupted:
            console.print(f"the viewer stays up at {viewer.url}; press Ctrl-C to exit")
            try:
                while True:
                    time.sleep(0.5)
            except KeyboardInterrupt:
                pass
        viewer.close()
    return summary


# Every key of a run's summary.json; those the run did not reach are null, and ``reason`` says why.
SUMMARY_KEYS = ("episode_id", "house_seed", "variant", "interrupted", "reason", "success", "spl", "steps",
                "path_length", "d_star", "final_distance", "status", "nvsm_runs", "n_objects", "gaussians",
                "wall_time_s", "episode_time_s", "viewer_ms_per_step")


def _save_run(out: str, ep, variant: str, state: dict, result, interrupted: bool, wall: float, bridge) -> dict:
    """Write map.ply, trajectory.json and summary.json (keys: :data:`SUMMARY_KEYS`) into ``out``."""
    agent = state["agent"]
    n_ply = 0
    if agent is not None and agent.mapper.map.n_active:
        n_ply = io.save_ply(agent.mapper.map, os.path.join(out, "map.ply"))
    io.atomic_write_bytes(os.path.join(out, "trajectory.json"), json.dumps(state["traj"]).encode())
    summary = dict.fromkeys(SUMMARY_KEYS)
    summary.update(episode_id=ep.episode_id, house_seed=ep.house_seed, variant=variant, interrupted=interrupted,
                   d_star=ep.d_star, steps=len(state["traj"]), gaussians=n_ply, wall_time_s=wall,
                   n_objects=len(agent.db) if agent is not None else 0,
                   viewer_ms_per_step=(1e3 * bridge.seconds / bridge.steps) if bridge is not None and bridge.steps
                   else None)
    if result is not None:
        r = result.to_json()
        summary.update({k: r[k] for k in ("success", "spl", "steps", "path_length", "final_distance", "status",
                                          "nvsm_runs", "n_objects")})
        summary["episode_time_s"] = r["wall_time"]
    else:
        summary["reason"] = (f"interrupted (Ctrl-C) after {len(state['traj'])} steps: the episode was not judged"
                             if interrupted else "the episode did not finish")
    io.atomic_write_bytes(os.path.join(out, "summary.json"), json.dumps(summary, indent=1).encode())
    return summary
