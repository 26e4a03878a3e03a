"""The open plane taught by imitation (docs/training.md, "Smooth driving"): ODV-PPO-Drop cloned from the ORCA robot
in position swap with one human (and, with ``--worlds``, in the other open-plane scenarios too), then DAgger rounds
(`socnav.rl.imitation`); smoothness_table.py evaluates it beside the ORCA robot and the PPO policy on the same
held-out episodes.

    python docs/analysis/open_plane_dagger.py --steps 100000 --rounds 10 --out runs/open_plane_dagger10.zip
    python docs/analysis/open_plane_dagger.py --steps 100000 --rounds 20 \
        --worlds position_swap:1 circle_crossing circle_interaction random --out runs/open/mixed.zip
    # the runs in docs/training.md predate --train-seeds and --feature-range: --train-seeds 0 --feature-range 0
    python docs/analysis/smoothness_table.py "shipped policy=pretrained" "DAgger=runs/open_plane_dagger10.zip" \
        --episodes 200 --seed 5000
"""

from __future__ import annotations

import argparse
from pathlib import Path

from socnav.config import load_config
from socnav.controllers import make_controller
from socnav.envs.vec_env import SocialNavVecEnv
from socnav.rl.imitation import Demonstrations, clone, collect_demonstrations, track_feature_range
from socnav.rl.persistence import save_policy
from socnav.rl.presets import make_model

FEATURE_RANGE_SEEDS = 9_000_000  # --feature-range's episodes: beyond the DAgger rounds' (100,000 seeds apart)
WORLD_SEEDS = 1_000_000  # the collections of the k-th world of --worlds start k times this far apart


def parse_world(text: str) -> dict:
    """``scenario`` or ``scenario:n_humans`` -> the world's config overrides (the scenario's default crowd), checked
    as a world; a bad one is a ValueError naming what is wrong."""
    scenario, _, humans = text.partition(":")
    if humans and not humans.isdigit():
        raise ValueError(f"{text!r}: the number of humans after ':' must be a whole number, got {humans!r}")
    world = {"scenario": scenario, **({"n_humans": int(humans)} if humans else {})}
    load_config(world)  # ConfigError (a ValueError): the field and the allowed values
    return world


def teach(args: argparse.Namespace) -> None:
    worlds = args.worlds
    envs = [SocialNavVecEnv(world, n_envs=16) for world in worlds]
    model = make_model("odv-ppo-drop", envs[0], seed=args.seed)
    teachers = [make_controller("orca", env.config) for env in envs]
    steps = args.steps // len(envs)  # --steps labels per round, shared equally by the worlds
    demonstrations: Demonstrations | None = None
    for round_ in range(1 + args.rounds):
        parts = []
        for index, (env, teacher) in enumerate(zip(envs, teachers, strict=True)):
            env.seed(args.train_seeds + WORLD_SEEDS * index + args.seed + 100_000 * round_)
            parts.append(collect_demonstrations(env, teacher, steps, gamma=model.gamma,
                                                driver=None if round_ == 0 else model.policy))
        part = Demonstrations.concatenate(parts) if len(parts) > 1 else parts[0]
        demonstrations = part if demonstrations is None else Demonstrations.concatenate([demonstrations, part])
        losses = clone(model.policy, demonstrations, epochs=10 if round_ == 0 else 2, seed=args.seed + round_)
        print(f"round {round_}: {len(part):,} labels, action_mse {losses[-1]['action_mse']:.3f}", flush=True)
    if args.feature_range:  # imitation tracks no feature range (feature uncertainty); PPO's rollouts do
        envs[0].seed(args.train_seeds + FEATURE_RANGE_SEEDS)
        track_feature_range(model.policy, envs[0], args.feature_range)
    metadata = {"algo": "odv-ppo-drop", "algo_config": model.algo_config, "seed": args.seed, "timesteps": 0,
                "env_config": load_config(worlds[0]).model_dump(mode="json")}
    save_policy(model.policy, args.out, metadata)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=50_000, help="labelled steps per round")
    parser.add_argument("--rounds", type=int, default=5, help="DAgger rounds after the first clone")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--train-seeds", type=int, default=10_000_000, metavar="BASE",
                        help="the collections' episodes start at this seed, far from the evaluations' (0-199, "
                             "5000-5199); the runs in docs/training.md used 0")
    parser.add_argument("--feature-range", type=int, default=20_000, metavar="STEPS",
                        help="set the feature range over STEPS steps the final policy drives (0: leave it unset)")
    parser.add_argument("--worlds", nargs="+", default=["position_swap:1"], metavar="SCENARIO[:HUMANS]",
                        help="the open-plane worlds the ORCA robot teaches in, --steps shared equally; the first is "
                             "the policy's world (default: position swap with one human)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    try:
        args.worlds = [parse_world(text) for text in args.worlds]
    except ValueError as exc:
        parser.error(f"--worlds: {exc}")
    teach(args)


if __name__ == "__main__":
    main()
