"""A two-stage curriculum in the doorway (docs/maps.md, "Learning among walls"): a policy trained in the empty
doorway with the route observation, fine-tuned with the default crowd, then evaluated on seeds 0-199.

    socnav train --config EMPTY.yaml --algo odv-ppo-drop --seed 0 --timesteps 100000 --out runs/doorway_empty
    python docs/analysis/doorway_curriculum.py runs/doorway_empty/model.zip --steps 200000 --out runs/doorway.zip

EMPTY.yaml is configs/env/doorway_route.yaml with ``n_humans: 0``. ``--config`` names another crowded world (e.g.
configs/env/doorway_route_collision20.yaml, the same world with a collision penalty of 20); ``--eval-seed`` the
first evaluation seed (validation episodes are drawn from 100,000 on, apart from the reported seeds 0-199).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from socnav.config import load_config
from socnav.envs import make_vec_env
from socnav.envs.rollout import rollout_episodes
from socnav.rl.convert import to_sb3
from socnav.rl.persistence import load_policy, save_policy

CROWDED = Path(__file__).resolve().parents[2] / "configs" / "env" / "doorway_route.yaml"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("start", type=Path, help="the policy trained in the empty doorway")
    parser.add_argument("--steps", type=int, default=200_000)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--config", type=Path, default=CROWDED, help="the crowded world to fine-tune in")
    parser.add_argument("--eval-seed", type=int, default=0)
    parser.add_argument("--eval-episodes", type=int, default=200)
    args = parser.parse_args()
    config = load_config(args.config)
    model = to_sb3(args.start, env=make_vec_env(config, n_envs=16), seed=0)
    start = time.monotonic()
    model.learn(args.steps)
    metadata = dict(load_policy(args.start).socnav_metadata)
    metadata.update(env_config=config.model_dump(mode="json"), timesteps=int(metadata.get("timesteps", 0)) + args.steps)
    policy = load_policy(save_policy(model.policy, args.out, metadata))
    records = rollout_episodes(policy, config, args.eval_episodes, seed=args.eval_seed, n_envs=50)
    print(f"{time.monotonic() - start:.0f} s", records["outcome"].value_counts().to_dict())


if __name__ == "__main__":
    main()
