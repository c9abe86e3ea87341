"""The reference walker's carried shift and the LLU captioner.

    python benchmarks/olivia_walker_shift.py --seeds 309,329,304,308 --times 1-8

``human.walker_rollout`` (what ``features.expert_action``, the LLU's captioner, forks from a state)
starts with no lateral shift chosen, while the walker in the reference episode carries the shift it
chose last (``WalkerCarry.offset``; the cost ``w_change`` x (shift - carried)² makes it keep to it).
This replays the walker's episode with its carry and, at each of ``--times`` (s), prints the shift
it carries, its y, the action of its own next 4 s (``ref``), of a rollout from the same state with
the shift reset to 0 (``fresh``: what the captioner says) and of one with the carried shift
(``kept``: should equal ``ref``). Stop 44 (results.md): on doorway 309 and 329 ``fresh`` says keep
left at 2 s where the reference keeps right.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="doorway")
    ap.add_argument("--seeds", default="309,329,304,308")
    ap.add_argument("--times", default="1-8", help="whole seconds (default 1-8)")
    args = ap.parse_args(argv)

    import jax
    import jax.numpy as jnp
    from olivia_llu_trace import parse_seeds

    from splatsearch.social.convoi import pedsim
    from splatsearch.social.convoi.geometry import F32
    from splatsearch.social.convoi.human import HumanWalkerConfig, WalkerCarry, make_walker_world, walker_step
    from splatsearch.social.convoi.runner import GOAL_TOLERANCE
    from splatsearch.social.convoi.scenarios import ROBOT_RADIUS, make_scenario
    from splatsearch.social.olivia.captions import ACTIONS
    from splatsearch.social.olivia.features import FUTURE_STRIDE, HORIZON, action_of, extend_to_goal, future_in_frame

    cfg = HumanWalkerConfig()

    def rollout(scn, world, carry, sf, key, n):
        out = [np.asarray(carry.pose)]
        for _ in range(n):
            carry, *_ = walker_step(carry, world, key, cfg, sf)
            out.append(np.asarray(carry.pose))
            if np.linalg.norm(out[-1][:2] - scn.goal) < GOAL_TOLERANCE:
                break
        return np.stack(out)

    def action(scn, poses, pose):
        if np.linalg.norm(poses[-1, :2] - np.asarray(scn.goal)[:2]) < GOAL_TOLERANCE:
            poses = extend_to_goal(poses, scn.goal)
        return ACTIONS[action_of(future_in_frame(poses, 0, np.asarray(pose, np.float64)))]

    steps = [10 * s for s in parse_seeds(args.times)]
    for seed in parse_seeds(args.seeds):
        t0 = time.time()
        scn = make_scenario(args.scenario, seed)
        sf = pedsim.SocialForceConfig(dt=scn.dt, robot_radius=ROBOT_RADIUS)
        world = make_walker_world(scn, cfg)
        key = jax.random.PRNGKey(scn.seed)
        carry = WalkerCarry(jnp.asarray(scn.start, F32), jnp.zeros(2, F32), scn.peds, jnp.asarray(0, jnp.int32),
                            jnp.asarray(0.0, F32))
        carries, poses = [carry], [np.asarray(carry.pose)]
        for _ in range(scn.max_steps):  # the reference episode, as runner.run_episode(scn, "human") drives it
            carry, *_ = walker_step(carry, world, key, cfg, sf)
            carries.append(carry)
            poses.append(np.asarray(carry.pose))
            if np.linalg.norm(poses[-1][:2] - scn.goal) < GOAL_TOLERANCE:
                break
        own = extend_to_goal(np.stack(poses), scn.goal)
        out = []
        for t in steps:
            if t >= len(carries):
                break
            c = carries[t]
            ref = ACTIONS[action_of(future_in_frame(own, t, np.asarray(poses[t], np.float64)))]
            n = FUTURE_STRIDE * HORIZON
            fresh = action(scn, rollout(scn, world, c._replace(offset=jnp.asarray(0.0, F32)), sf, key, n), poses[t])
            kept = action(scn, rollout(scn, world, c, sf, key, n), poses[t])
            out.append(f"{t / 10:.0f}s shift {float(c.offset):+.1f} y {poses[t][1]:+.2f} ref {ref} fresh {fresh} kept {kept}")
        print(seed, f"({time.time() - t0:.0f} s)", " | ".join(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
