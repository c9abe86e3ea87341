"""Social-force pedestrians and the seeded scenarios."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from splatsearch.social.convoi import pedsim
from splatsearch.social.convoi.geometry import pad_capsules
from splatsearch.social.convoi.scenarios import (
    GRID,
    SCENARIOS,
    THESIS_SCENARIOS,
    make_scenario,
)

CFG = pedsim.SocialForceConfig()
FAR_ROBOT = jnp.array([100.0, 100.0])


def simulate(state, caps, valid, n, seed=0, robot=FAR_ROBOT, compiled_length=160):
    # always the same scan length (one compile for the whole file), cut to n afterwards
    assert n <= compiled_length
    robots = jnp.broadcast_to(jnp.asarray(robot, jnp.float32), (compiled_length, 2))
    _, pos, infos = pedsim.simulate(state, caps, valid, robots, jnp.zeros((compiled_length, 2), jnp.float32),
                                    jax.random.PRNGKey(seed), 0, CFG)
    return None, np.concatenate([np.asarray(state.pos)[None], np.asarray(pos)[:n]]), infos


def corridor():
    return pad_capsules(np.array([[-1, -1.0, 11, -1.0, 0.05], [-1, 1.0, 11, 1.0, 0.05]], np.float32), 16)


def test_two_people_head_on_pass_each_other_without_overlap_or_entering_walls():
    caps, valid = corridor()
    st = pedsim.make_state([[0.0, 0.05], [10.0, -0.05]], [[[10.0, 0.0]], [[0.0, 0.0]]], [1.2, 1.2])
    _, traj, infos = simulate(st, jnp.asarray(caps), jnp.asarray(valid), 160)
    assert not np.asarray(infos.robot_contact).any() and int(np.asarray(infos.wall_contacts).sum()) == 0
    a, b = traj[:, 0], traj[:, 1]
    assert np.linalg.norm(a[-1] - [10.0, 0.0]) < 0.5 and np.linalg.norm(b[-1] - [0.0, 0.0]) < 0.5
    assert np.linalg.norm(a - b, axis=1).min() >= 0.5 - 1e-3  # hard collisions resolved: never overlap
    assert np.abs(traj[:, :2, 1]).max() <= 1.0 - 0.05 - 0.25 + 1e-3  # never inside a wall
    # they swerved to pass: some lateral separation when they met
    meet = np.argmin(np.abs(a[:, 0] - b[:, 0]))
    assert abs(a[meet, 1] - b[meet, 1]) > 0.4
    # in a 2 m corridor the forces alone let them touch for a few steps as they meet (8 in this
    # run); the hard-collision pass resolves those, and there are none away from the meeting
    touching = np.flatnonzero(np.asarray(infos.ped_contacts)[:160])
    assert 0 < len(touching) <= 12 and np.all(np.abs(touching + 1 - meet) <= 10), (touching, meet)


def test_overlapping_people_are_counted_and_pushed_apart():
    caps, valid = pad_capsules(np.zeros((0, 5), np.float32), 16)
    st = pedsim.make_state([[0.0, 0.0], [0.2, 0.0], [3.0, 0.0]], [[[5.0, 0.0]], [[-5.0, 0.0]], [[3.0, 2.0]]],
                           [1.0, 1.0, 1.0])
    new, info = pedsim.step(st, jnp.asarray(caps), jnp.asarray(valid), FAR_ROBOT, jnp.zeros(2),
                            jax.random.PRNGKey(0), CFG)
    assert int(info.ped_contacts) == 1 and int(info.wall_contacts) == 0  # one overlapping pair
    p = np.asarray(new.pos)
    assert np.linalg.norm(p[0] - p[1]) >= 2 * float(st.radius[0]) - 1e-3


def test_static_group_holds_its_formation_and_robot_contact_is_reported():
    caps, valid = pad_capsules(np.zeros((0, 5), np.float32), 16)
    ring = np.array([[0.7, 0.0], [-0.35, 0.6], [-0.35, -0.6]], np.float32)
    st = pedsim.make_state(ring, [[p] for p in ring], [0.6] * 3, group=[0, 0, 0])
    _, traj, _ = simulate(st, jnp.asarray(caps), jnp.asarray(valid), 100)
    assert np.abs(traj[-1, :3] - ring).max() < 0.15
    # a robot parked on top of a member is a contact, reported and not resolved away
    _, info = pedsim.step(st, jnp.asarray(caps), jnp.asarray(valid), jnp.asarray(ring[0]), jnp.zeros(2),
                          jax.random.PRNGKey(0), CFG)
    assert bool(np.asarray(info.robot_contact)[0]) and not np.asarray(info.robot_contact)[1:3].any()


def test_people_make_way_for_the_robot():
    caps, valid = corridor()
    st = pedsim.make_state([[0.0, 0.0]], [[[8.0, 0.0]]], [1.0])
    robot = np.array([3.0, 0.15], np.float32)  # a little off the person's line: no symmetric deadlock
    _, free, _ = simulate(st, jnp.asarray(caps), jnp.asarray(valid), 90)
    _, blocked, _ = simulate(st, jnp.asarray(caps), jnp.asarray(valid), 90, robot=jnp.asarray(robot))
    d = np.linalg.norm(blocked[:, 0] - robot, axis=1)
    assert d.min() > 0.5  # never ran into the robot
    assert np.abs(blocked[:, 0, 1]).max() > np.abs(free[:, 0, 1]).max() + 0.2  # went around it
    assert blocked[-1, 0, 0] > robot[0] + 1.0  # and got past


def test_forecast_reproduces_the_future_for_the_assumed_robot_motion():
    scn = make_scenario("crossing", 3)
    caps, valid = (jnp.asarray(a) for a in scn.padded_capsules())
    key = jax.random.PRNGKey(scn.seed)
    robot, rvel = jnp.array([1.0, 0.0]), jnp.array([0.5, 0.0])
    fut = np.asarray(pedsim.forecast(scn.peds, caps, valid, robot, rvel, key, 7, 20, CFG))
    st, rp = scn.peds, robot
    for k in range(20):
        st, _ = pedsim.step(st, caps, valid, rp, rvel, pedsim.step_key(key, 7 + k), CFG)
        rp = rp + CFG.dt * rvel
        np.testing.assert_allclose(fut[k], np.asarray(st.pos), atol=1e-5)


@pytest.mark.parametrize("name", SCENARIOS)
def test_scenarios_are_deterministic_per_seed(name):
    a, b, c = make_scenario(name, 4), make_scenario(name, 4), make_scenario(name, 5)
    for x, y in zip(a.peds, b.peds):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    np.testing.assert_array_equal(a.capsules, b.capsules)
    np.testing.assert_array_equal(a.start, b.start)
    assert not np.array_equal(np.asarray(a.peds.pos), np.asarray(c.peds.pos))
    # simulation is deterministic for a seed too
    caps, valid = (jnp.asarray(v) for v in a.padded_capsules())
    _, t1, _ = simulate(a.peds, caps, valid, 20, seed=a.seed)
    _, t2, _ = simulate(b.peds, caps, valid, 20, seed=b.seed)
    np.testing.assert_array_equal(t1, t2)


@pytest.mark.parametrize("name", SCENARIOS)
def test_scenario_geometry_is_sound(name):
    scn = make_scenario(name, 1)
    f = np.asarray(scn.field().values)
    assert f.shape == GRID.shape
    route = scn.global_path()

    def clearance(xy):  # nearest-cell lookup in numpy (no compile per array length)
        rc = GRID.world_to_cell(xy)
        return f[rc[:, 0], rc[:, 1]]

    assert clearance(route).min() > 0.25  # the route is drivable
    assert np.linalg.norm(route[0] - scn.start[:2]) < 1e-5 and np.linalg.norm(route[-1] - scn.goal) < 1e-5
    pos = np.asarray(scn.peds.pos)[np.asarray(scn.peds.active)]
    assert clearance(pos).min() > 0.25  # nobody starts in a wall
    assert 1 <= scn.n_people <= 12
    if name in THESIS_SCENARIOS[2:]:
        assert len(scn.groups) == 2


def test_bad_scenario_arguments_raise():
    with pytest.raises(ValueError, match="unknown scenario"):
        make_scenario("mall", 0)
    with pytest.raises(ValueError, match="seed"):
        make_scenario("hallway", -1)
    with pytest.raises(ValueError, match="waypoint"):
        pedsim.make_state([[0, 0]], [[]], [1.0])
