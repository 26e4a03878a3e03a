"""What a policy does in the last steps before it hits a wall, beside what its ORCA teacher would do there
(docs/maps.md, "Why DAgger hits walls"): per map scenario, over the episodes that end against a wall.

    python docs/analysis/wall_labels.py runs/maps_dagger12/cloned_clone.zip --episodes 200 --seed 0
"""

from __future__ import annotations

import argparse
import collections
from typing import Any

import numpy as np

from socnav.config import load_config
from socnav.controllers import OrcaController
from socnav.envs.rollout import rollout_episodes
from socnav.rl.persistence import load_policy

SCENARIOS = ("corridor", "doorway", "intersection", "room")
LAST_STEPS = 6


class PolicyBesideTeacher:
    """Acts as `policy` (deterministic) and keeps, per step, its action, the teacher's and the teacher's ORCA
    velocity as a share of the preferred speed."""

    def __init__(self, policy: Any, teacher: OrcaController) -> None:
        self.policy, self.teacher = policy, teacher
        self.last: tuple[np.ndarray, ...] = ()

    def on_episode_start(self, envs: np.ndarray) -> None:
        self.teacher.on_episode_start(envs)

    def predict(self, observation: dict[str, np.ndarray], deterministic: bool = True, **_: Any) -> tuple[Any, None]:
        actions, _ = self.policy.predict(observation, deterministic=True)
        labels, _ = self.teacher.predict(observation)
        velocity = self.teacher.desired_velocity(observation)
        share = np.linalg.norm(velocity, axis=1) / np.maximum(observation["robot"][:, 3], 1e-6)
        self.last = (np.asarray(actions), np.asarray(labels), share)
        return actions, None


class History:
    """Each episode's steps as `PolicyBesideTeacher` saw them (a `rollout_episodes` observer)."""

    def __init__(self, actor: PolicyBesideTeacher) -> None:
        self.actor = actor
        self.steps: dict[int, list[tuple[Any, ...]]] = collections.defaultdict(list)

    def on_step(self, observation: Any, actions: Any, result: Any, running: np.ndarray) -> None:
        actions, labels, share = self.actor.last
        for env, episode in enumerate(running):
            if episode >= 0:
                self.steps[int(episode)].append((actions[env], labels[env], share[env]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("policy")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--teacher-turn", choices=("velocity", "goal", "goal-if-behind"), default="velocity")
    args = parser.parse_args()
    policy = load_policy(args.policy)
    world = policy.socnav_metadata["env_config"]
    print(f"The last {LAST_STEPS} steps of the episodes that end against a wall: mean actions in [-1, 1] (speed -1: "
          "stopped; turn +-1: the most it turns), the policy's and the ORCA teacher's on the same states")
    print("| scenario | wall episodes | policy speed | teacher speed | teacher's ORCA speed / preferred | "
          "policy's turn (abs) | teacher's turn (abs) | teacher's turn flips side (% of steps) |")
    print("|:--|--:|--:|--:|--:|--:|--:|--:|")
    for scenario in SCENARIOS:
        config = load_config({"scenario": scenario, "scan": world["scan"], "planner": world["planner"],
                              "reward": world["reward"]})
        actor = PolicyBesideTeacher(policy, OrcaController(config, stopped_turn=args.teacher_turn))
        history = History(actor)
        records = rollout_episodes(actor, config, args.episodes, seed=args.seed, n_envs=50, progress=False,
                                   observer=history)
        walls = records.loc[records["outcome"] == "collision_wall", "episode"].tolist()
        last = [step for episode in walls for step in history.steps[episode][-LAST_STEPS:]]
        if not last:
            print(f"| {scenario} | 0 | - | - | - | - | - | - |")
            continue
        actions, labels, share = (np.array(column) for column in zip(*last, strict=True))
        flips = [np.sign(a[1][1]) != np.sign(b[1][1]) for episode in walls
                 for a, b in zip(history.steps[episode][-LAST_STEPS:], history.steps[episode][-LAST_STEPS + 1:],
                                 strict=False)]
        print(f"| {scenario} | {len(walls)} | {actions[:, 0].mean():.2f} | {labels[:, 0].mean():.2f} | "
              f"{share.mean():.2f} | {np.abs(actions[:, 1]).mean():.2f} | {np.abs(labels[:, 1]).mean():.2f} | "
              f"{100 * np.mean(flips):.0f} |", flush=True)


if __name__ == "__main__":
    main()
