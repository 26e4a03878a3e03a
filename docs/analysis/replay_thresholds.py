"""Replay one Table 3 safety unit's episodes with a given thresholds file and fallback holds: an A/B of rules on the
very episodes (seeds, strengths, repeats, dropout masks) the unit played, outside the experiment engine.

    python docs/analysis/replay_thresholds.py RUN_DIR PERTURBATION [--estimator mc] [--thresholds FILE]
        [--holds 0,1,2]

RUN_DIR: a finished `socnav run configs/experiments/table3.yaml` directory; PERTURBATION: one of its safety units
(observation_noise, heading_noise, speed_noise, faster_humans, more_humans); --thresholds: default the run's own
calibrated true-state thresholds (`calibrate-true/<estimator>/thresholds.yaml`); each --holds value replaces their
`hold_steps` (default: the file's own). Prints, per hold and strength, the collisions over the unit's repeats and
the fallback's share of steps (at the unperturbed strength: the false activation). MC-dropout only (the ensemble needs all members).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from socnav.envs.perturbations import perturbed_config
from socnav.envs.rollout import rollout_episodes
from socnav.rl.persistence import load_policy
from socnav.safety import FallbackCounter, SafePolicy, Thresholds, load_thresholds
from socnav.uncertainty import MC_SEED, MCDropoutEstimator


def replay(run_dir: Path, perturbation: str, thresholds: Thresholds, estimator: str = "mc") -> list[str]:
    """One text cell per strength: collisions and fallback share of the unit's episodes under `thresholds`."""
    unit = json.loads((run_dir / "safety" / estimator / perturbation / "unit.json").read_text())
    params = unit["params"]
    policy = load_policy(run_dir / unit["deps"][0] / "model.zip")
    cells = []
    for strength in params["strengths"]:
        config = perturbed_config(params["env"], params["perturbation"], strength)
        collisions = fallback_steps = steps = 0
        for repeat in range(params["repeats"]):
            # the unit's seeds and a fresh, seeded estimator per run: the masks the unit's variants saw
            seed = params["seed"] + repeat * params["episodes"]
            mc = MCDropoutEstimator(policy, k=params["k"], seed=MC_SEED)
            safe = SafePolicy(policy, mc, thresholds, config, window=params["window"])
            counter = FallbackCounter(safe)
            records = rollout_episodes(safe, config, params["episodes"], seed=seed, n_envs=params["n_envs"],
                                       observer=counter)
            collisions += int((records["outcome"] == "collision").sum())
            fallback_steps += sum(counter.per_episode(records["episode"]))
            steps += int(records["length"].sum())
        cells.append(f"strength {strength:g}: {collisions} collisions, fallback {100 * fallback_steps / steps:.2f} %")
    return cells


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("perturbation")
    parser.add_argument("--estimator", default="mc", choices=["mc"])
    parser.add_argument("--thresholds", type=Path, default=None)
    parser.add_argument("--holds", default=None, help="comma-separated hold_steps values (default: the file's)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    path = args.thresholds or args.run_dir / "calibrate-true" / args.estimator / "thresholds.yaml"
    base = load_thresholds(path)
    holds = [base.hold_steps] if args.holds is None else [int(h) for h in args.holds.split(",")]
    for hold in holds:
        thresholds = Thresholds.create(base.model_dump(), hold_steps=hold)
        print(f"hold {hold}: " + " | ".join(replay(args.run_dir, args.perturbation, thresholds, args.estimator)),
              flush=True)


if __name__ == "__main__":
    main()
