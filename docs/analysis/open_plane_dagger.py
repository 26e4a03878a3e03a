"""The shipped policy's world taught by imitation (docs/training.md, "Smooth driving"): ODV-PPO-Drop cloned from the
ORCA robot in position swap with one human, then DAgger rounds (`socnav.rl.imitation`), evaluated beside the ORCA
robot and the shipped policy on the same held-out episodes, with jerk and path irregularity as multiples of the ORCA
robot's.

    python docs/analysis/open_plane_dagger.py --steps 50000 --rounds 5 --out runs/open_plane_dagger.zip --episodes 200
    python docs/analysis/open_plane_dagger.py --steps 100000 --rounds 10 --out runs/open_plane_dagger10.zip
"""

from __future__ import annotations

import argparse
from pathlib import Path

from scipy.stats import binomtest

from socnav.config import load_config
from socnav.controllers import make_controller
from socnav.envs.rollout import rollout_episodes
from socnav.envs.vec_env import SocialNavVecEnv
from socnav.rl.imitation import Demonstrations, clone, collect_demonstrations
from socnav.rl.persistence import load_policy, save_policy
from socnav.rl.presets import make_model

WORLD = {"scenario": "position_swap", "n_humans": 1}


def _rate(hits: int, n: int) -> str:
    interval = binomtest(hits, n).proportion_ci(0.95, method="exact")
    return f"{100 * hits / n:.1f} [{100 * interval.low:.1f}, {100 * interval.high:.1f}]"


def teach(args: argparse.Namespace) -> None:
    env = SocialNavVecEnv(WORLD, n_envs=16)
    model = make_model("odv-ppo-drop", env, seed=args.seed)
    teacher = make_controller("orca", env.config)
    demonstrations: Demonstrations | None = None
    for round_ in range(1 + args.rounds):
        env.seed(args.seed + 100_000 * round_)
        part = collect_demonstrations(env, teacher, args.steps, gamma=model.gamma,
                                      driver=None if round_ == 0 else model.policy)
        demonstrations = part if demonstrations is None else Demonstrations.concatenate([demonstrations, part])
        losses = clone(model.policy, demonstrations, epochs=10 if round_ == 0 else 2, seed=args.seed + round_)
        print(f"round {round_}: {len(part):,} labels, action_mse {losses[-1]['action_mse']:.3f}", flush=True)
    metadata = {"algo": "odv-ppo-drop", "algo_config": model.algo_config, "seed": args.seed, "timesteps": 0,
                "env_config": load_config(WORLD).model_dump(mode="json")}
    save_policy(model.policy, args.out, metadata)


def evaluate(args: argparse.Namespace) -> None:
    world = load_config(WORLD)
    actors = {"ORCA robot": make_controller("orca", world), "shipped policy": load_policy("pretrained"),
              "cloned + DAgger": load_policy(args.out)}
    rows = {label: rollout_episodes(actor, world, args.episodes, seed=args.eval_seed, n_envs=50, progress=False)
            for label, actor in actors.items()}
    orca = rows["ORCA robot"]
    print("| policy | Goal % [95 % CI] | Collision % [95 % CI] | jerk (m/s³) | x ORCA | path irregularity (rad) "
          "| x ORCA |")
    print("|---|---|---|---|---|---|---|")
    for label, records in rows.items():
        n, outcome = len(records), records["outcome"]
        jerk, irregularity = records["jerk_mean"].mean(), records["path_irregularity"].mean()
        print(f"| {label} | {_rate(int((outcome == 'goal').sum()), n)} | "
              f"{_rate(int((outcome == 'collision').sum()), n)} | {jerk:.2f} | {jerk / orca['jerk_mean'].mean():.1f} | "
              f"{irregularity:.3f} | {irregularity / orca['path_irregularity'].mean():.1f} |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=50_000, help="labelled steps per round")
    parser.add_argument("--rounds", type=int, default=5, help="DAgger rounds after the first clone")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--eval-seed", type=int, default=5000, help="first held-out episode (docs/training.md's)")
    parser.add_argument("--evaluate-only", action="store_true")
    args = parser.parse_args()
    if not args.evaluate_only:
        teach(args)
    evaluate(args)


if __name__ == "__main__":
    main()
