"""``scan.people``: the range scan also stops at the humans' bodies, as a real lidar's beams do. Checked against
ray-disc intersections computed here by hand, beside the walls-only scan of the same world."""

from __future__ import annotations

import math

import numpy as np
import pytest

import socnav
from socnav.sim.geometry import scan_angles


def _ray_to_disc(origin: np.ndarray, angle: float, centre: np.ndarray, radius: float) -> float:
    """Distance along the ray from `origin` at `angle` to the disc's boundary (inf if it misses or lies behind)."""
    direction = np.array([math.cos(angle), math.sin(angle)])
    offset = centre - origin
    along = float(offset @ direction)
    across_squared = float(offset @ offset) - along * along
    if across_squared > radius * radius:
        return math.inf
    hit = along - math.sqrt(radius * radius - across_squared)
    return hit if hit >= 0.0 else math.inf


@pytest.mark.parametrize("config", [
    {"scenario": "circle_crossing", "n_humans": 6},
    {"scenario": "doorway", "occlusion": True},
])
def test_each_beam_reads_the_nearer_of_the_wall_and_the_first_person(config):
    beams, max_range = 90, 6.0
    worlds = [socnav.make_vec_env({**config, "scan": {"beams": beams, "range": max_range, "people": people}},
                                  n_envs=3) for people in (False, True)]
    for env in worlds:
        env.seed(4)
        env.reset()
    for _ in range(15):  # the same episodes step alike: the scan is observed, it moves nobody
        observations = [env.step(np.tile([0.5, 0.2], (3, 1)).astype(np.float32))[0] for env in worlds]
    walls_only, with_people = (observation["scan"] for observation in observations)
    world = worlds[1].world
    angle_min, increment = scan_angles(beams, 2.0 * math.pi)
    seen_a_person = 0
    for env in range(3):
        origin, heading = world.positions[env, 0], float(world.heading[env])
        for beam in range(beams):
            angle = heading + angle_min + beam * increment
            person = min((_ray_to_disc(origin, angle, world.positions[env, j], float(world.radii[env, j]))
                          for j in range(1, world.positions.shape[1]) if world.active[env, j]), default=math.inf)
            expected = min(float(walls_only[env, beam]), person, max_range)
            assert with_people[env, beam] == pytest.approx(expected, abs=1e-4)
            seen_a_person += person < walls_only[env, beam]
    assert seen_a_person > 0  # the check above compared some beams that end at a person
    assert np.all(with_people <= walls_only + 1e-6)


def test_the_scan_without_people_is_unchanged_by_the_option_being_off():
    config = {"scenario": "corridor", "scan": {"beams": 36}}
    default, explicit = (socnav.make_vec_env(c, n_envs=2) for c in (config, {**config,
                                                                              "scan": {"beams": 36, "people": False}}))
    for env in (default, explicit):
        env.seed(0)
    np.testing.assert_array_equal(default.reset()["scan"], explicit.reset()["scan"])
