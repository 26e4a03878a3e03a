"""How many collisions can the safety layer prevent at most? The plain policy vs the same policy with the fallback
taking over at EVERY approaching step (no uncertainty or proximity gate), per perturbation of Table 3.

    python docs/analysis/safety_ceiling.py runs/table3-quick/train/position_swap/odv-ppo-drop/seed0/model.zip

Prints collisions over the same episode seeds and the share the always-on fallback prevents: the ceiling for any
thresholds of the rule (`c_ap` and the cautious controller still see the robot's possibly noisy observation).
"""

from __future__ import annotations

import argparse

import socnav
from socnav.envs.perturbations import perturbation_override
from socnav.envs.rollout import rollout_episodes
from socnav.safety import SafePolicy, Thresholds
from socnav.uncertainty import MCDropoutEstimator

TABLE3_WORLD = {"scenario": "position_swap", "n_humans": 1, "personal_space": [0.3, 0.4]}  # configs/experiments/table3.yaml
STRENGTHS = {"observation_noise": [1.0, 2.0], "heading_noise": [1.0, 2.0], "speed_noise": [0.6, 1.0],
             "faster_humans": [4.0, 8.0], "more_humans": [4.0, 7.0]}
ALWAYS_WHEN_APPROACHING = Thresholds.create(lambda_ep=0.0, lambda_feat=0.0, lambda_prox=1e6, beta1=0.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", help="policy file (or 'pretrained')")
    parser.add_argument("--episodes", type=int, default=150)
    args = parser.parse_args()
    policy = socnav.load_policy(args.model)
    print(f"{'perturbation':18s} {'strength':>8s} {'plain col.':>10s} {'always-on col.':>14s} {'prevented %':>11s}")
    for kind, strengths in STRENGTHS.items():
        totals = [0, 0]
        for strength in strengths:
            config = socnav.load_config({**TABLE3_WORLD, "perturbation": perturbation_override(kind, strength)})
            plain = rollout_episodes(policy, config, args.episodes, seed=0, n_envs=50)
            safe = SafePolicy(policy, MCDropoutEstimator(policy, k=20, seed=0), ALWAYS_WHEN_APPROACHING, config)  # perceived
            guarded = rollout_episodes(safe, config, args.episodes, seed=0, n_envs=50)
            counts = [int((frame["outcome"] == "collision").sum()) for frame in (plain, guarded)]
            totals = [totals[0] + counts[0], totals[1] + counts[1]]
            print(f"{kind:18s} {strength:8g} {counts[0]:10d} {counts[1]:14d}", flush=True)
        share = 100.0 * (totals[0] - totals[1]) / totals[0] if totals[0] else float("nan")
        print(f"{kind:18s} {'all':>8s} {totals[0]:10d} {totals[1]:14d} {share:11.1f}", flush=True)


if __name__ == "__main__":
    main()
