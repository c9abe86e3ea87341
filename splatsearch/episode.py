"""Run one instance-image-goal episode in the simulator with the SplatSearch agent."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

from splatsearch.agent import AgentConfig, SplatSearchAgent, StepInfo
from splatsearch.sim.env import HouseEnv
from splatsearch.sim.episodes import (
    Episode,
    EpisodeJudge,
    goal_image,
    house_for_episode,
    spl,
)


@dataclass
class EpisodeResult:
    """Outcome of one episode: success, SPL, steps, path length (m), d* (m), distance to the
    goal at the end (m), wall time (s), the agent's last status and the trajectory (T, 3)."""

    episode_id: int
    house_seed: int
    variant: str
    success: bool
    spl: float
    steps: int
    path_length: float
    d_star: float
    final_distance: float
    wall_time: float
    status: str
    nvsm_runs: int
    n_objects: int
    trajectory: list = field(default_factory=list)

    def to_json(self) -> dict:
        return asdict(self)


def run_episode(ep: Episode, config: AgentConfig | None = None, *, env: HouseEnv | None = None,
                on_step: Callable[[SplatSearchAgent, object, StepInfo], None] | None = None,
                max_steps: int | None = None) -> EpisodeResult:
    """Run ``ep`` to its end (stop or the step cap) and judge it (Habitat IIN rules).

    ``on_step(agent, observation, info)`` is called after every decision (progress bars, the
    viewer); raising ``KeyboardInterrupt`` in it ends the episode early as a failure.
    """
    config = config or AgentConfig()
    t0 = time.perf_counter()
    if env is None:
        env = HouseEnv(house_for_episode(ep), width=ep.goal_width, height=ep.goal_height)
    obj = next((o for o in env.house.objects if o.instance_id == ep.goal_instance_id), None)
    if obj is None:
        raise ValueError(f"the episode's goal instance {ep.goal_instance_id} is not in the given house")
    judge = EpisodeJudge(env.nav, obj, ep.success_distance)
    goal_frame = goal_image(env, ep)
    obs = env.reset(ep.start)
    # the goal frame goes to the detector only (its class masks, as a detector run on the goal image)
    agent = SplatSearchAgent(env.K, env.width, env.height, goal_frame.rgb, ep.goal_class, obs.pose, config=config,
                             goal_frame=goal_frame)
    cap = min(ep.max_steps, max_steps or ep.max_steps)
    traj = [obs.gt_pose.tolist()]
    info = StepInfo("none", "start")
    while True:
        info = agent.act(obs.frame.rgb, obs.frame.depth, obs.viewmat, obs.pose, obs.frame)
        if on_step is not None:
            on_step(agent, obs, info)
        if env.steps >= cap - 1 and info.action != "stop":
            info.action = "stop"  # the last allowed action: Habitat ends the episode here anyway
        obs = env.step(info.action)
        traj.append(obs.gt_pose.tolist())
        if obs.done or info.action == "stop":
            break
    xy = obs.gt_pose[:2]
    success = judge.success(xy)
    return EpisodeResult(
        episode_id=ep.episode_id, house_seed=ep.house_seed, variant=config.variant, success=bool(success),
        spl=spl(success, ep.d_star, env.path_length), steps=env.steps, path_length=float(env.path_length),
        d_star=float(ep.d_star), final_distance=float(judge.distance(xy)), wall_time=time.perf_counter() - t0,
        status=info.status, nvsm_runs=agent.nvsm_runs, n_objects=len(agent.db), trajectory=traj)
