"""Replayed humans (``humans.model: replay``, ``scenario: replay``) and mixed crowds (``humans.mix``).

Replay: the ETH/UCY trajectory files (``frame_id ped_id x y``, 2.5 Hz) are generated here, never downloaded; the
loader round trip, linear interpolation to the env's time step (values computed by hand), the errors (file and line
named), pedestrians entering and leaving mid-episode, the slot limit, Gymnasium's checker and determinism.
Mix: the shares over many episodes, the draw leaving every other draw of an episode unchanged, each model moving
its own humans, determinism; the default config stays bit-identical (test_human_models.py's golden episodes).
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import socnav
from socnav.config import ConfigError, load_config
from socnav.sim.humans import OrcaHumans, SocialForceHumans, TrajectoryFileError, make_human_model, replay, trajectories
from socnav.sim.humans.replay import interpolate_tracks, load_replay, read_trajectories
from socnav.sim.scenarios import get_scenario
from socnav.sim.world import CrowdWorld

DT = 0.25


def write_rows(path: Path, rows, separator: str = "\t") -> Path:
    """Rows (frame, ped, x, y) in the ETH/UCY text format, as TrajNet / Social-GAN write it (ids as floats)."""
    path.write_text("".join(f"{frame}{separator}{ped:.1f}{separator}{x:.2f}{separator}{y:.2f}\n"
                            for frame, ped, x, y in rows))
    return path


def crossing_rows(n_pedestrians: int = 8, seed: int = 0, offset=(100.0, -50.0), frames: int = 60):
    """Pedestrians walking straight lines at ~1.2 m/s through a 12 m square centred on `offset`, each between its
    own first and last frame (frame ids step by 10, as in ETH/UCY), sorted by frame as those files are."""
    rng = np.random.default_rng(seed)
    rows = []
    for ped in range(1, n_pedestrians + 1):
        first, length = int(rng.integers(0, frames // 2)), int(rng.integers(8, frames // 2))
        angle = rng.uniform(0.0, 2.0 * math.pi)
        start = rng.uniform(-6.0, 6.0, 2)
        velocity = 1.2 * np.array([math.cos(angle), math.sin(angle)])
        for j in range(length):
            x, y = start + velocity * 0.4 * j + np.asarray(offset)
            rows.append((10 * (first + j), ped, round(x, 2), round(y, 2)))
    return sorted(rows)


def replay_config(files, **env) -> dict:
    return {"scenario": "replay", "humans": {"model": "replay", "replay": {"files": [str(f) for f in files]}}, **env}


@pytest.fixture()
def scene(tmp_path) -> Path:
    return write_rows(tmp_path / "crossing.txt", crossing_rows())


# ---------------------------------------------------------------------------------------------------- the loader


def test_the_loader_reads_back_what_was_written(tmp_path):
    rows = crossing_rows(n_pedestrians=6, seed=3)
    recording = read_trajectories(write_rows(tmp_path / "scene.txt", rows))
    assert recording.frame_step == 10 and recording.n_rows == len(rows)
    first_frame = min(row[0] for row in rows)
    seen_order = list(dict.fromkeys(row[1] for row in rows))  # pedestrians in order of first appearance
    assert recording.ids.tolist() == seen_order
    for ped, samples, positions in zip(recording.ids, recording.samples, recording.positions, strict=True):
        mine = [row for row in rows if row[1] == ped]
        assert samples.tolist() == [(row[0] - first_frame) / 10 for row in mine]
        assert positions.tolist() == [[row[2], row[3]] for row in mine]


def test_spaces_comments_blank_lines_and_other_frame_steps(tmp_path):
    # frame ids stepping by 6; spaces instead of tabs; a comment and blank lines are skipped
    text = "# frame ped x y\n\n780 1 8.46 3.59\n786 1 9.57 3.79\n786 2 1.0 2.0   # a comment\n\n792 2 1.5 2.5\n"
    recording = read_trajectories(write_text(tmp_path / "eth.txt", text))
    assert recording.frame_step == 6 and recording.first_frame == 780
    assert [s.tolist() for s in recording.samples] == [[0.0, 1.0], [1.0, 2.0]]
    assert read_trajectories(tmp_path / "eth.txt", frame_step=3).samples[1].tolist() == [2.0, 4.0]


def write_text(path: Path, text: str | bytes) -> Path:
    (path.write_bytes if isinstance(text, bytes) else path.write_text)(text)
    return path


def test_interpolation_to_the_time_step_by_hand(tmp_path):
    # 2.5 Hz samples are 0.4 s apart: with dt = 0.25 s a step is 0.625 samples.
    # ped 1: frames 0, 10, 20 at (0, 0), (1, 0), (1, 2): samples u = 0, 1, 2.
    #   steps k = 0..3 (u = 0, 0.625, 1.25, 1.875; k = 4 is u = 2.5, after its last frame):
    #   (0, 0), (0.625, 0), (1, 0.25 * 2), (1, 0.875 * 2)
    # ped 2: frames 10, 30 at (4, 4), (2, 0): u = 1 .. 3, bridged over its missing frame 20;
    #   first step ceil(1 / 0.625) = 2 (u = 1.25), last floor(3 / 0.625) = 4 (u = 2.5): (4 - 0.25, 4 - 0.5),
    #   (4 - 0.875, 4 - 1.75), (4 - 1.5, 4 - 3)
    # ped 3: frames 10, 20: u = 1 .. 2 holds no step's time except k = 2 (u = 1.25) and 3 (u = 1.875)
    # ped 4: only frame 20 (u = 2): no step falls on it: an empty track
    path = write_text(tmp_path / "hand.txt", "0 1 0 0\n10 1 1 0\n10 2 4 4\n10 3 0 0\n20 1 1 2\n20 3 1 1\n"
                                             "20 4 9 9\n30 2 2 0\n")
    recording = read_trajectories(path)
    tracks = dict(zip(recording.ids, interpolate_tracks(recording, DT, 2.5), strict=True))
    first, xy = tracks[1.0]
    assert first == 0 and xy == pytest.approx(np.array([[0, 0], [0.625, 0], [1, 0.5], [1, 1.75]]), abs=1e-12)
    first, xy = tracks[2.0]
    assert first == 2 and xy == pytest.approx(np.array([[3.75, 3.5], [3.125, 2.25], [2.5, 1.0]]), abs=1e-12)
    first, xy = tracks[3.0]
    assert first == 2 and xy == pytest.approx(np.array([[0.25, 0.25], [0.875, 0.875]]), abs=1e-12)
    assert len(tracks[4.0][1]) == 0
    # on the grid of dt = 0.4 s (one step per sample) the samples come back exactly
    first, xy = dict(zip(recording.ids, interpolate_tracks(recording, 0.4, 2.5), strict=True))[1.0]
    assert first == 0 and np.array_equal(xy, [[0, 0], [1, 0], [1, 2]])

    # the env's scenes: centred on the file's bounding box ([0, 9] x [0, 9]: centre (4.5, 4.5)), ped 4 left out
    scenes = load_replay(load_config(replay_config([path])).humans.replay, DT)
    assert scenes.centres[0] == pytest.approx([4.5, 4.5])
    first, xy = scenes.track(0, 2.0)
    assert first == 2 and xy == pytest.approx(np.array([[3.75, 3.5], [3.125, 2.25], [2.5, 1.0]]) - 4.5, abs=1e-12)
    with pytest.raises(KeyError):
        scenes.track(0, 4.0)


BAD_FILES = [
    ("0 1 0 0\n10 1 1\n", "line 2: expected 4 columns (frame_id ped_id x y), found 3"),
    ("0 1 0 0 7\n", "line 1: expected 4 columns (frame_id ped_id x y), found 5"),
    ("0,1,0,0\n", "line 1: expected 4 columns"),
    ("0 1 0 0\n\n10 1 abc 0\n", "line 3: x is not a number: 'abc'"),
    ("0 one 0 0\n", "line 1: ped_id is not a number: 'one'"),
    ("0 1 0 0\n10 1 nan 0\n", "line 2: x is not a finite number: 'nan'"),
    ("0 1 0 -inf\n", "line 1: y is not a finite number: '-inf'"),
    ("0 1 0 1e999\n", "line 1: y is not a finite number: '1e999'"),
    ("0 1 0 0\n0.5 2 1 1\n", "line 2: frame_id 0.5 is not a whole number"),
    ("0 1 0 0\n20 1 1 0\n10 2 3 3\n10 1 2 0\n", "line 4: frame 10 of pedestrian 1 does not come after its frame 20 "
                                                "on line 2"),
    ("0 1 0 0\n0 1 1 1\n", "line 2: frame 0 of pedestrian 1 does not come after its frame 0 on line 1"),
    ("", "holds no trajectories"),
    ("# only a comment\n\n", "holds no trajectories"),
    (b"0 1 0 0\n10 1 \xff\xfe 0\n", "line 2: not UTF-8 text"),
]


@pytest.mark.parametrize(("content", "expected"), BAD_FILES)
def test_a_bad_file_names_the_file_and_the_line(tmp_path, content, expected):
    path = write_text(tmp_path / "bad.txt", content)
    with pytest.raises(TrajectoryFileError) as error:
        read_trajectories(path)
    assert str(path) in str(error.value) and expected in str(error.value), str(error.value)
    # the config refuses it too, naming the field
    with pytest.raises(ConfigError) as config_error:
        load_config(replay_config([path]))
    assert "humans.replay.files:" in str(config_error.value) and expected in str(config_error.value)


def test_file_size_bound(tmp_path, monkeypatch):
    # A sparse file one byte over the bound (64 MiB): refused from its size, nothing read.
    sparse = tmp_path / "huge.txt"
    with open(sparse, "wb") as stream:
        stream.truncate(replay.MAX_FILE_BYTES + 1)
    assert replay.MAX_FILE_BYTES == 64 << 20
    with pytest.raises(ConfigError) as error:
        load_config(replay_config([sparse]))
    assert f"has {replay.MAX_FILE_BYTES + 1:,} bytes; socnav reads trajectory files of at most" in str(error.value)
    # the reader enforces the bound while reading (a smaller bound, patched)
    small = write_rows(tmp_path / "small.txt", crossing_rows(n_pedestrians=2))
    monkeypatch.setattr(trajectories, "MAX_FILE_BYTES", 64)
    with pytest.raises(TrajectoryFileError, match=f"trajectory file {small} is larger than 64 bytes"):
        read_trajectories(small)


def test_config_errors(tmp_path, scene, monkeypatch):
    for config, expected in (
        (replay_config([tmp_path / "missing.txt"]), "humans.replay.files: trajectory file not found"),
        (replay_config([tmp_path]), "is not a regular file"),
        ({"scenario": "replay", "humans": {"model": "replay"}}, "model: replay needs humans.replay.files"),
        (replay_config([scene], humans={"model": "replay", "replay": {"files": [str(scene)], "sample_rate": 0}}),
         "humans.replay.sample_rate"),
    ):
        with pytest.raises(ConfigError) as error:
            load_config(config)
        assert expected in str(error.value), str(error.value)
    # the scenario and the model go together, both ways
    with pytest.raises(ConfigError, match=re.escape("scenario: replay needs humans.model: replay")):
        load_config({"scenario": "replay"})
    with pytest.raises(ConfigError, match=re.escape("humans.model: replay humans need scenario: replay")):
        load_config({**replay_config([scene]), "scenario": "circle_crossing"})
    with pytest.raises(ConfigError, match=re.escape("perturbation.human_model: replay humans need scenario: replay")):
        load_config({"perturbation": {"human_model": "replay"}})
    with pytest.raises(ConfigError, match="cannot walk by 'social_force'"):
        load_config({**replay_config([scene]), "perturbation": {"human_model": "social_force"}})
    # paths are stored absolute: the config means the same files from any working directory
    monkeypatch.chdir(scene.parent)
    relative = load_config(replay_config([scene.name]))
    assert relative.humans.replay.files == [str(scene.resolve())]


# ---------------------------------------------------------------------------------------------------- replayed episodes


def _staged_world(path: Path, n_humans: int = 4, n_envs: int = 1, seed: int = 0) -> CrowdWorld:
    world = CrowdWorld(load_config(replay_config([path], n_humans=n_humans, max_humans=max(n_humans, 1))), n_envs)
    for env in range(n_envs):
        world.seed(env, seed + env)
    world.reset()
    return world


def test_humans_follow_their_tracks_and_enter_and_leave(tmp_path):
    # A walks through the whole recording; B enters at frame 40 (u = 4: step ceil(6.4) = 7) and leaves after
    # frame 80 (u = 8: its last step floor(12.8) = 12). The recording is shorter than an episode: it starts at 0.
    rows = [(10 * j, 1, -8.0 + 0.5 * j, 9.0) for j in range(21)]
    rows += [(10 * j, 2, 9.0, -8.0 + 0.4 * j) for j in range(4, 9)]
    path = write_rows(tmp_path / "enter_leave.txt", sorted(rows))
    world = _staged_world(path)
    scenes = world.human_model.scenes
    assert world.script is world.human_model and world.human_model.step[0] == 0
    a_first, a_track = scenes.track(0, 1.0)
    b_first, b_track = scenes.track(0, 2.0)
    assert (a_first, len(a_track), b_first, len(b_track)) == (0, 33, 7, 6)
    slot_of = {}
    for k in range(40):
        active = world.active[0, 1:].copy()
        pedestrians = set(world.human_model.slot_pedestrian[0, 1:][active].tolist())
        expected = {0} | ({1} if 7 <= k <= 12 else set())
        # A's global index is 0, B's 1 (sorted by first step)
        assert pedestrians == (expected if k < 33 else expected - {0}), k
        for slot in np.flatnonzero(world.active[0]):
            if slot == 0:
                continue
            p = world.human_model.slot_pedestrian[0, slot]
            slot_of.setdefault(p, slot)
            first, track = (a_first, a_track) if p == 0 else (b_first, b_track)
            assert np.array_equal(world.positions[0, slot], track[k - first]), (k, p)
        observation = world.observe()
        assert observation["humans_mask"][0].sum() == world.active[0, 1:].sum()
        world.step(np.array([[-1.0, 0.0]]))  # the robot stands
    assert slot_of == {0: 1, 1: 2}
    # velocities are those of the last step, from the recording
    assert world.velocities[0, 1] == pytest.approx([0.0, 0.0])  # A has left (its slot is padding)


def test_a_full_scene_keeps_the_humans_closest_to_the_robots_path(tmp_path):
    # six pedestrians standing at different distances from the centre; two slots
    rows = [(10 * j, ped, x, y) for j in range(30) for ped, (x, y) in
            enumerate([(0.0, 3.0), (0.0, -0.5), (-4.0, 4.0), (4.0, -4.0), (1.0, 0.2), (6.0, 6.0)], start=1)]
    path = write_rows(tmp_path / "crowd.txt", sorted(rows))
    for seed in range(5):
        world = _staged_world(path, n_humans=2, seed=seed)
        start, goal = world.positions[0, 0], world.goals[0, 0]
        centred = np.array([[0.0, 3.0], [0.0, -0.5], [-4.0, 4.0], [4.0, -4.0], [1.0, 0.2], [6.0, 6.0]]) - 1.0
        distance = [_segment(p, start, goal) for p in centred]
        closest = set(np.argsort(distance)[:2].tolist())
        assert set(world.human_model.slot_pedestrian[0, 1:].tolist()) == closest
        assert world.active[0].sum() == 3


def _segment(p, a, b):
    s = np.clip(np.dot(p - a, b - a) / np.dot(b - a, b - a), 0.0, 1.0)
    return float(np.linalg.norm(p - a - s * (b - a)))


def test_late_arrivals_find_no_slot_when_the_slots_are_taken(tmp_path):
    rows = [(10 * j, ped, float(ped), 0.0) for j in range(30) for ped in (1, 2)]
    rows += [(10 * j, 3, 0.0, 5.0) for j in range(5, 30)]  # appears at u = 5 (step 8)
    world = _staged_world(write_rows(tmp_path / "late.txt", sorted(rows)), n_humans=2)
    for _ in range(12):
        world.step(np.array([[-1.0, 0.0]]))
    assert sorted(world.human_model.slot_pedestrian[0, 1:].tolist()) == [0, 1]


def test_the_replay_scenario_passes_the_gymnasium_checker_and_episodes_end(scene):
    env = socnav.make_env(replay_config([scene]), render_mode="rgb_array")
    check_env(env, skip_render_check=False)
    outcomes = []
    for seed in range(3):
        observation, _ = env.reset(seed=seed)
        for _ in range(10_000):
            observation, reward, terminated, truncated, info = env.step(np.array([0.6, 0.0]))
            assert np.isfinite(reward) and all(np.isfinite(value).all() for value in observation.values())
            if terminated or truncated:
                outcomes.append(info["outcome"])
                assert info["episode"]["disturbance"] == 0.0, "replayed humans ignore the robot"
                break
    assert len(outcomes) == 3
    image = env.render()
    assert image.shape[2] == 3


def test_the_robot_crosses_the_centred_scene(scene):
    config = load_config(replay_config([scene]))
    state = get_scenario("replay").sample(np.random.default_rng(0), 40, config)
    path = state.goals[:, 0] - state.positions[:, 0]
    assert np.linalg.norm(path, axis=1) == pytest.approx(np.full(40, 10.0))
    assert (state.positions[:, 0] + state.goals[:, 0]) / 2 == pytest.approx(np.zeros((40, 2)), abs=1e-12)
    angles = np.arctan2(path[:, 1], path[:, 0])
    assert np.ptp(angles) > 3.0, "directions are drawn per episode"
    humans = state.positions[:, 1:][state.active[:, 1:]]
    assert np.abs(humans).max() < 12.0, "the scene is centred on the origin (the file is around (100, -50))"
    for env in range(40):  # the robot starts clear of the pedestrians present
        present = state.positions[env, 1:][state.active[env, 1:]]
        if len(present):
            assert np.linalg.norm(present - state.positions[env, 0], axis=1).min() >= replay.START_CLEARANCE


def test_replayed_episodes_are_deterministic_and_batch_independent(scene):
    config = replay_config([scene], n_humans=4, max_humans=4)

    actions = np.random.default_rng(0).uniform(-1, 1, (120, 3, 2)).astype(np.float32)

    def play(envs, seed):
        vec = socnav.make_vec_env(config, n_envs=len(envs))
        vec.seed(seed)
        observations = [vec.reset()]
        for step in range(120):
            observation, _, _, _ = vec.step(actions[step, envs])
            observations.append(observation)
        return {key: np.stack([o[key] for o in observations]) for key in observations[0]}

    first, again = play([0, 1, 2], 5), play([0, 1, 2], 5)
    for key in first:
        assert np.array_equal(first[key], again[key]), key
    single = play([1], 6)  # env 1 of the batch seeded 5 is the single env seeded 6
    for key in first:
        assert np.array_equal(first[key][:, 1], single[key][:, 0]), key
    assert (first["humans_mask"].sum(axis=-1) < 4).any() and (np.diff(first["humans_mask"].sum(-1), axis=0) != 0).any()


def test_a_world_keeps_its_scenes_when_the_read_cache_drops_them(scene):
    world = _staged_world(scene)
    replay.read_scenes.cache_clear()  # e.g. many other replay configs read in this process since
    assert load_replay(world.config.humans.replay, DT) is world.human_model.scenes
    world.reset()
    world.step(np.array([[0.0, 0.0]]))


def test_several_files(tmp_path):
    a = write_rows(tmp_path / "a.txt", crossing_rows(seed=1, offset=(0.0, 0.0), frames=40))
    b = write_rows(tmp_path / "b.txt", crossing_rows(seed=2, offset=(50.0, 50.0), frames=200))
    config = load_config(replay_config([a, b]))
    scenes = load_replay(config.humans.replay, config.time_step)
    assert len(scenes.files) == 2 and scenes.scene_lo[1] == scenes.scene_hi[0]
    picked = [scenes.plan(np.random.default_rng(seed), 4, 10.0, 10).scene for seed in range(200)]
    share_b = np.mean(picked)
    expected = scenes.scene_steps[1] / scenes.scene_steps.sum()
    assert abs(share_b - expected) < 0.12, (share_b, expected)


# ---------------------------------------------------------------------------------------------------- mixed crowds

MIX = {"orca": 0.3, "social_force": 0.7}


def _mixed_world(mix, n_envs=8, seed=0, **config) -> CrowdWorld:
    world = CrowdWorld(load_config({"scenario": "circle_crossing", "humans": {"mix": mix}, **config}), n_envs)
    for env in range(n_envs):
        world.seed(env, seed + env)
    world.reset()
    return world


def test_the_shares_over_many_episodes_match_the_configured_ones():
    world = _mixed_world(MIX, n_envs=64, n_humans=10)
    assert world.config.humans.model == "mix" and world.mix.names == ["orca", "social_force"]
    counts = np.zeros(2)
    for _ in range(20):
        humans = world.active & world.humans_slots
        counts += np.bincount(world.model_index[humans], minlength=2)
        world.reset()
    share = counts[1] / counts.sum()
    sigma = math.sqrt(0.3 * 0.7 / counts.sum())  # 12,800 humans: 0.004
    assert counts.sum() == 64 * 10 * 20 and abs(share - 0.7) < 4 * sigma, share
    # and every episode is a mix of its own (not all humans of one episode share a model)
    assert len({tuple(row) for row in world.model_index[:, 1:].tolist()}) > 1


def test_the_model_draw_leaves_every_other_draw_of_an_episode_unchanged():
    plain, mixed = _mixed_world({"orca": 1.0}, seed=3), _mixed_world(MIX, seed=3)
    reference = CrowdWorld(load_config({"scenario": "circle_crossing"}), 8)
    for env in range(8):
        reference.seed(env, 3 + env)
    reference.reset()
    for world in (plain, mixed):
        for name in ("positions", "goals", "radii", "preferred_speeds", "personal_space", "cooperation", "active",
                     "attentive", "heading", "noise_keys"):
            assert np.array_equal(getattr(world, name), getattr(reference, name)), name
    # a mix of ORCA alone is the ORCA world, step for step
    rng = np.random.default_rng(0)
    for _ in range(40):
        actions = rng.uniform(-1, 1, (8, 2))
        a, b = plain.step(actions), reference.step(actions)
        assert np.array_equal(a.reward, b.reward) and np.array_equal(plain.positions, reference.positions)


def test_each_model_moves_its_own_humans():
    world = _mixed_world(MIX, n_envs=6, seed=11, human_fov_deg=360, n_humans=8, max_humans=8)
    for _ in range(6):
        world.step(np.full((6, 2), 0.3))
    compute = world.active & world.humans_slots
    velocities = world.human_velocities()
    crowd = world.crowd()
    orca = OrcaHumans.from_config(world.config).velocities(crowd, compute)
    social_force = SocialForceHumans.from_config(world.config).velocities(crowd, compute)
    is_sf = world.model_index == 1
    assert is_sf[compute].any() and (~is_sf)[compute].any()
    assert np.array_equal(velocities[compute & is_sf], social_force[compute & is_sf])
    assert np.array_equal(velocities[compute & ~is_sf], orca[compute & ~is_sf])
    # each model's own arrival distance and interaction range, per human
    assert np.all(world.arrival_distances[is_sf & compute] == 0.5)
    assert np.all(world.arrival_distances[~is_sf & compute] == world.config.goal_tolerance)
    assert np.all(np.isinf(world.interaction_ranges[is_sf & compute]))
    assert np.all(world.interaction_ranges[~is_sf & compute] == world.config.orca.neighbor_dist)
    assert world.human_model_names(0)[1:] == [["orca", "social_force"][k] for k in world.model_index[0, 1:]]


def test_mixed_episodes_are_deterministic_and_pass_the_checker():
    config = {"scenario": "random", "humans": {"mix": MIX}}
    check_env(socnav.make_env(config), skip_render_check=True)

    def play(seed):
        env = socnav.make_env(config)
        observation, _ = env.reset(seed=seed)
        rng = np.random.default_rng(seed)
        rows = [observation["humans"]]
        for _ in range(80):
            observation, _, terminated, truncated, _ = env.step(rng.uniform(-1, 1, 2))
            rows.append(observation["humans"])
            if terminated or truncated:
                observation, _ = env.reset()
        return np.stack(rows), env.unwrapped.world.model_index.copy()

    (a, index_a), (b, index_b) = play(4), play(4)
    assert np.array_equal(a, b) and np.array_equal(index_a, index_b)


def test_a_mix_builds_each_of_its_models_once():
    model = make_human_model(load_config({"humans": {"mix": MIX}}))
    assert [type(m) for m in model.models] == [OrcaHumans, SocialForceHumans] and model.shares == [0.3, 0.7]
    zero = make_human_model(load_config({"humans": {"mix": {"orca": 0.0, "social_force": 1.0}}}))
    assert zero.names == ["social_force"]


def test_a_mixed_world_is_described_with_its_shares():
    from socnav.config import describe_world

    config = load_config({"scenario": "circle_crossing", "humans": {"mix": {"orca": 0.25, "social_force": 0.75}}})
    assert "mixed humans (orca 25 %, social_force 75 %)" in describe_world(config)
