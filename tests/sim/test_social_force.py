"""Social force humans against their oracle, PySocialForce 1.1.2 (`pip install pysocialforce==1.1.2`, test extra).

PySocialForce's `Simulator` runs the same crowds with its step width set to the env's time step and its initial
speeds (max speed = 1.3 x initial speed) set to the humans' v_pref. One step from identical states must agree to
1e-5 and 50-step trajectories to 1e-3 m (measured: both agree to ~1e-14). The robot, attention, personal space and the
field of view are checked against PySocialForce scenes built to mean the same.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from socnav.config import SocialForceConfig, load_config
from socnav.sim.humans import Crowd, SocialForceHumans

DT = 0.25
ONE_STEP_TOLERANCE = 1e-5
TRAJECTORY_TOLERANCE = 1e-3  # metres, after 50 steps


def model(**parameters) -> SocialForceHumans:
    config = load_config({"time_step": DT, "humans": {"model": "social_force", "social_force": parameters}})
    return SocialForceHumans.from_config(config)


# ---------------------------------------------------------------------------------------------------- crowds


def random_crowd(rng: np.random.Generator, n: int, density: float):
    """n agents in a square of `density` agents per m^2, random velocities up to 1.3 v_pref, a quarter of them
    within 0.7 m of their goal (the braking and stopping branches)."""
    side = math.sqrt(n / density)
    positions = rng.uniform(-side / 2, side / 2, (n, 2))
    goals = rng.uniform(-side, side, (n, 2))
    v_pref = rng.uniform(0.5, 1.5, n)
    heading = rng.uniform(-math.pi, math.pi, n)
    velocities = np.stack([np.cos(heading), np.sin(heading)], axis=1) * (rng.uniform(0, 1.3, n) * v_pref)[:, None]
    near = n // 4
    offset = rng.uniform(-math.pi, math.pi, near)
    goals[:near] = positions[:near] + np.stack([np.cos(offset), np.sin(offset)], 1) * rng.uniform(0, 0.7, near)[:, None]
    return positions, velocities, goals, v_pref


def batch(crowds) -> Crowd:
    """Crowds of different sizes as one `Crowd` of E environments, padded with inactive slots (neutral pairs)."""
    n_envs, n_slots = len(crowds), max(len(crowd[0]) for crowd in crowds) + 1  # one padding slot at least
    positions, velocities, goals = (np.zeros((n_envs, n_slots, 2)) for _ in range(3))
    max_speeds, active = np.zeros((n_envs, n_slots)), np.zeros((n_envs, n_slots), dtype=bool)
    for env, (p, v, g, v_pref) in enumerate(crowds):
        n = len(p)
        positions[env, :n], velocities[env, :n], goals[env, :n], max_speeds[env, :n] = p, v, g, v_pref
        active[env, :n] = True
        positions[env, n:] = 0.1  # padding sits in the crowd: it must exert no force
    return Crowd(positions=positions, velocities=velocities, goals=goals, radii=np.full((n_envs, n_slots), 0.3),
                 max_speeds=max_speeds, active=active, radius_pad=np.zeros((n_envs, n_slots, n_slots)),
                 avoidance_share=np.full((n_envs, n_slots, n_slots), 0.5),
                 sees=np.ones((n_envs, n_slots, n_slots), dtype=bool))


def run(humans: SocialForceHumans, crowd: Crowd, steps: int, compute: np.ndarray | None = None) -> None:
    """`steps` steps in place, moving the computed agents as the world does: v from the model, p <- p + v dt."""
    compute = crowd.active if compute is None else compute
    for _ in range(steps):
        velocities = humans.velocities(crowd, compute)
        crowd.positions[...] += np.where(compute[..., None], velocities, 0.0) * DT
        crowd.velocities[...] = velocities


def simulator(psf, positions, velocities, goals, v_pref):
    """PySocialForce's default simulator on these agents, stepping by DT with max speeds 1.3 v_pref."""
    sim = psf.Simulator(np.concatenate([positions, velocities, goals], axis=1).astype(float))
    sim.peds.step_width = DT
    sim.peds.initial_speeds = np.asarray(v_pref, dtype=float).copy()
    sim.peds.state = sim.peds.state  # recomputes max_speeds = max_speed_multiplier * initial_speeds
    return sim


def oracle(psf, positions, velocities, goals, v_pref, steps: int):
    sim = simulator(psf, positions, velocities, goals, v_pref).step(steps)
    return sim.peds.pos().copy(), sim.peds.vel().copy()


# ---------------------------------------------------------------------------------------------------- the oracle


def test_defaults_are_pysocialforces_published_ones(psf):
    published = psf.utils.DefaultConfig()
    desired, social = published.sub_config("desired_force"), published.sub_config("social_force")
    scene, fov = published.sub_config("scene"), published.sub_config("ped_repulsive_force")
    ours = SocialForceConfig()
    assert ours.relaxation_time == desired("relaxation_time")
    assert ours.goal_threshold == desired("goal_threshold")
    assert ours.desired_force_factor == desired("factor")
    assert ours.social_force_factor == social("factor")
    assert (ours.lambda_importance, ours.gamma, ours.n, ours.n_prime) == (
        social("lambda_importance"), social("gamma"), social("n"), social("n_prime"))
    assert ours.max_speed_multiplier == scene("max_speed_multiplier")
    assert (ours.fov_phi, ours.fov_factor) == (fov("fov_phi"), fov("fov_factor"))
    # PySocialForce's simulator applies no field of view to its social force (only to the repulsion it leaves out)
    assert not ours.field_of_view
    assert [type(force).__name__ for force in psf.Simulator(np.zeros((1, 6))).forces][:3] == [
        "DesiredForce", "SocialForce", "ObstacleForce"]


SIZES = (2, 3, 5, 8, 13, 21, 34, 60)


@pytest.mark.parametrize("seed", range(4))
def test_one_step_matches_pysocialforce_on_random_crowds(psf, seed):
    rng = np.random.default_rng(seed)
    crowds = [random_crowd(rng, n, density=rng.uniform(0.2, 2.0)) for n in SIZES]
    crowd = batch(crowds)  # every crowd size in one batched call
    run(model(), crowd, steps=1)
    worst = 0.0
    for env, state in enumerate(crowds):
        n = len(state[0])
        positions, velocities = oracle(psf, *state, steps=1)
        worst = max(worst, np.abs(crowd.velocities[env, :n] - velocities).max(),
                    np.abs(crowd.positions[env, :n] - positions).max())
    assert worst < ONE_STEP_TOLERANCE, worst


@pytest.mark.parametrize("seed", range(3))
def test_fifty_step_trajectories_match_pysocialforce(psf, seed):
    # Crowds of up to 1 person per 3 m^2 do not amplify rounding: both simulators stay within ~1e-14 m.
    rng = np.random.default_rng(100 + seed)
    crowds = [random_crowd(rng, int(rng.integers(2, 61)), density=rng.uniform(0.05, 0.35)) for _ in range(6)]
    crowd = batch(crowds)
    run(model(), crowd, steps=50)
    for env, state in enumerate(crowds):
        n = len(state[0])
        positions, _ = oracle(psf, *state, steps=50)
        assert np.abs(crowd.positions[env, :n] - positions).max() < TRAJECTORY_TOLERANCE
        assert np.abs(crowd.positions[env, :n] - state[0]).max() > 1.0, "the crowd must actually walk"


def test_parameters_reach_the_model(psf, tmp_path):
    # Every force parameter changed at once, PySocialForce given the same values through its config file (its
    # PedState reads max_speed_multiplier from the file's top level, never from [scene]: set on it directly).
    parameters = {"relaxation_time": 0.7, "goal_threshold": 0.3, "desired_force_factor": 1.4,
                  "social_force_factor": 3.0, "lambda_importance": 1.5, "gamma": 0.5, "n": 1.5, "n_prime": 2.5,
                  "max_speed_multiplier": 1.1}
    toml = tmp_path / "config.toml"
    toml.write_text(
        f"[desired_force]\nfactor = {parameters['desired_force_factor']}\n"
        f"relaxation_time = {parameters['relaxation_time']}\ngoal_threshold = {parameters['goal_threshold']}\n"
        f"[social_force]\nfactor = {parameters['social_force_factor']}\n"
        f"lambda_importance = {parameters['lambda_importance']}\ngamma = {parameters['gamma']}\n"
        f"n = {parameters['n']}\nn_prime = {parameters['n_prime']}\n"
    )
    rng = np.random.default_rng(7)
    state = random_crowd(rng, 12, density=0.5)
    crowd = batch([state])
    run(model(**parameters), crowd, steps=1)
    sim = psf.Simulator(np.concatenate(state[:3], axis=1), config_file=str(toml))
    sim.peds.step_width, sim.peds.max_speed_multiplier = DT, parameters["max_speed_multiplier"]
    sim.peds.initial_speeds = state[3].copy()
    sim.peds.state = sim.peds.state
    sim.step(1)
    assert np.abs(crowd.velocities[0, :12] - sim.peds.vel()).max() < ONE_STEP_TOLERANCE
    # and the defaults differ enough that the check means something
    default = batch([state])
    run(model(), default, steps=1)
    assert np.abs(default.velocities[0, :12] - sim.peds.vel()).max() > 1e-2


# ---------------------------------------------------------------------------------------------------- the robot


def robot_scene(rng, n_humans=8):
    """Slot 0 a robot driving through a crowd of humans (slots 1..), as in the world."""
    humans = random_crowd(rng, n_humans, density=0.6)
    robot = (np.array([[0.2, -0.4]]), np.array([[0.6, 0.3]]), np.array([[5.0, 5.0]]), np.array([1.0]))
    state = tuple(np.concatenate([r, h]) for r, h in zip(robot, humans, strict=True))
    crowd = batch([state])
    compute = crowd.active.copy()
    compute[0, 0] = False  # the policy moves the robot
    return state, crowd, compute


def test_the_robot_is_one_more_agent(psf):
    state, crowd, compute = robot_scene(np.random.default_rng(11))
    velocities = model().velocities(crowd, compute)
    _, expected = oracle(psf, *state, steps=1)
    n = len(state[0])
    assert np.abs(velocities[0, 1:n] - expected[1:]).max() < ONE_STEP_TOLERANCE
    assert np.array_equal(velocities[0, 0], state[1][0]), "the robot keeps its own velocity"


def test_humans_that_do_not_see_the_robot_walk_as_if_it_were_absent(psf):
    # `sees[e, i, 0]` False: inattentive, robot not yet in view, or robot_visible false (the world decides which)
    state, crowd, compute = robot_scene(np.random.default_rng(12))
    blind = np.array([False, True, False, True, True, False, False, True, False])  # slot 0 is the robot
    crowd.sees[0, np.flatnonzero(blind), 0] = False
    velocities = model().velocities(crowd, compute)
    n = len(state[0])
    _, with_robot = oracle(psf, *state, steps=1)
    _, without_robot = oracle(psf, *(array[1:] for array in state), steps=1)
    for human in range(1, n):
        expected = without_robot[human - 1] if blind[human] else with_robot[human]
        assert np.abs(velocities[0, human] - expected).max() < ONE_STEP_TOLERANCE, human
    assert np.abs(with_robot[1:] - without_robot).max() > 1e-3, "the robot must matter in this scene"


def test_personal_space_makes_the_robot_seem_nearer_by_it(psf):
    # radius_pad[e, i, 0] = r_prox,i shortens the robot's distance in human i's force: PySocialForce with the
    # robot moved r_prox,i towards human i (same direction, distance - r_prox,i) gives human i the same velocity.
    state, crowd, compute = robot_scene(np.random.default_rng(13))
    n = len(state[0])
    pads = np.random.default_rng(14).uniform(0.1, 0.7, n)
    distances = np.linalg.norm(state[0][1:] - state[0][0], axis=1)
    pads[1:] = np.minimum(pads[1:], 0.9 * distances)  # never past the human (the model caps d - pad at 0)
    crowd.radius_pad[0, :n, 0] = pads
    velocities = model().velocities(crowd, compute)
    _, unpadded = oracle(psf, *state, steps=1)
    moved_any = False
    for human in range(1, n):
        positions = state[0].copy()
        towards = (positions[human] - positions[0]) / distances[human - 1]
        positions[0] = positions[0] + pads[human] * towards
        _, expected = oracle(psf, positions, *state[1:], steps=1)
        assert np.abs(velocities[0, human] - expected[human]).max() < ONE_STEP_TOLERANCE, human
        moved_any |= bool(np.abs(unpadded[human] - expected[human]).max() > 1e-4)
    assert moved_any, "personal space must change some human's step in this scene"


def test_field_of_view_weights_pysocialforces_pair_forces(psf):
    # With field_of_view on, each pair force f_ij of PySocialForce's SocialForce (computed on the pair alone) is
    # weighted by PySocialForce's FieldOfView: 1 inside the cone of half-angle phi around the desired direction,
    # fov_factor outside; then PySocialForce's own velocity step.
    rng = np.random.default_rng(21)
    positions, velocities, goals, v_pref = state = random_crowd(rng, 9, density=0.8)
    n = len(positions)
    crowd = batch([state])
    humans = model(field_of_view=True, fov_phi=80.0, fov_factor=0.3)
    ours = humans.velocities(crowd, crowd.active)[0, :n]

    pair_forces = np.zeros((n, n, 2))
    for i in range(n):
        for j in range(n):
            if i != j:
                pair = simulator(psf, positions[[i, j]], velocities[[i, j]], goals[[i, j]], v_pref[[i, j]])
                pair_forces[i, j] = pair.forces[1].get_force()[0]  # SocialForce, factor 5.1 included
    sim = simulator(psf, *state)
    weights = psf.fieldofview.FieldOfView(phi=80.0, out_of_view_factor=0.3)(sim.peds.desired_directions(),
                                                                          -pair_forces)
    assert 0 < (weights[~np.eye(n, dtype=bool)] < 1).sum() < n * (n - 1), "some pairs in view, some out of it"
    force = sim.forces[0].get_force() + np.sum(weights[..., None] * pair_forces, axis=1)
    sim.peds.step(force)
    assert np.abs(ours - sim.peds.vel()).max() < ONE_STEP_TOLERANCE
    assert np.abs(model().velocities(crowd, crowd.active)[0, :n] - ours).max() > 1e-3, "the weighting matters"


def rotated(state, angle: float):
    rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    positions, velocities, goals, v_pref = state
    return positions @ rotation.T, velocities @ rotation.T, goals @ rotation.T, v_pref


def test_theta_is_left_unwrapped_as_in_pysocialforce_unless_wrap_theta(psf):
    # theta = angle(t) - angle(u) is not wrapped by PySocialForce: when t and u straddle the -x direction, |theta|
    # is near 2 pi and the pair's force all but vanishes, so the same encounter turned by 180 degrees differs.
    # The default reproduces PySocialForce; wrap_theta gives Moussaid et al.'s angle in [-pi, pi).
    # Agent 0 walks +x, drifting up, towards agent 1 standing 2 m ahead: u points to -x just above the axis, t just
    # below it, so PySocialForce's theta is about -2 pi + 0.17 instead of 0.17.
    encounter = (np.array([[0.0, 0.1], [2.0, 0.0]]), np.array([[1.0, 0.2], [0.0, 0.0]]),
                 np.array([[9.0, 0.1], [2.0, 5.0]]), np.array([1.0, 1.0]))
    turned = rotated(encounter, math.pi)
    for state in (encounter, turned):
        ours = model().velocities(batch([state]), batch([state]).active)[0, :2]
        assert np.abs(ours - oracle(psf, *state, steps=1)[1]).max() < ONE_STEP_TOLERANCE
    velocity = {
        wrap: [model(wrap_theta=wrap).velocities(batch([state]), batch([state]).active)[0, :2]
               for state in (encounter, turned)] for wrap in (False, True)}
    # agent 0's velocity in the turned encounter should be its velocity turned by 180 degrees, -v
    assert np.abs(velocity[False][0][0] + velocity[False][1][0]).max() > 0.05, "PySocialForce's artefact"
    assert np.abs(velocity[True][0] + velocity[True][1]).max() < 1e-12, "wrapped: the turned encounter is the same"


def test_wrap_theta_makes_the_model_rotation_equivariant():
    rng = np.random.default_rng(31)
    state = random_crowd(rng, 20, density=0.8)
    n = len(state[0])
    errors = {}
    for wrap in (False, True):
        humans = model(wrap_theta=wrap)
        reference = humans.velocities(batch([state]), batch([state]).active)[0, :n]
        errors[wrap] = 0.0
        for angle in np.linspace(0.3, 2 * math.pi, 7, endpoint=False):
            turned = rotated(state, angle)
            expected = rotated((reference, reference, reference, None), angle)[0]
            velocities = humans.velocities(batch([turned]), batch([turned]).active)[0, :n]
            errors[wrap] = max(errors[wrap], np.abs(velocities - expected).max())
    assert errors[True] < 1e-9 and errors[False] > 1e-3, errors


def test_agents_not_computed_or_inactive_keep_their_velocity():
    rng = np.random.default_rng(5)
    crowd = batch([random_crowd(rng, 6, density=0.5), random_crowd(rng, 3, density=0.5)])
    compute = crowd.active.copy()
    compute[0, 2] = compute[1, 0] = False
    velocities = model().velocities(crowd, compute)
    keep = ~compute
    assert np.array_equal(velocities[keep], crowd.velocities[keep])
    assert not np.allclose(velocities[compute], crowd.velocities[compute])
    assert np.all(np.linalg.norm(velocities[compute], axis=-1)
                  <= 1.3 * crowd.max_speeds[compute] * (1 + 1e-12)), "capped at the max speed"
