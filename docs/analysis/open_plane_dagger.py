"""The shipped policy's world taught by imitation (docs/training.md, "Smooth driving"): ODV-PPO-Drop cloned from the
ORCA robot in position swap with one human, then DAgger rounds (`socnav.rl.imitation`); smoothness_table.py evaluates
it beside the ORCA robot and the shipped policy on the same held-out episodes.

    python docs/analysis/open_plane_dagger.py --steps 100000 --rounds 10 --out runs/open_plane_dagger10.zip
    python docs/analysis/smoothness_table.py "shipped policy=pretrained" "DAgger=runs/open_plane_dagger10.zip" \
        --episodes 200 --seed 5000
"""

from __future__ import annotations

import argparse
from pathlib import Path

from socnav.config import load_config
from socnav.controllers import make_controller
from socnav.envs.vec_env import SocialNavVecEnv
from socnav.rl.imitation import Demonstrations, clone, collect_demonstrations
from socnav.rl.persistence import save_policy
from socnav.rl.presets import make_model

WORLD = {"scenario": "position_swap", "n_humans": 1}


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=50_000, help="labelled steps per round")
    parser.add_argument("--rounds", type=int, default=5, help="DAgger rounds after the first clone")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    teach(parser.parse_args())


if __name__ == "__main__":
    main()
