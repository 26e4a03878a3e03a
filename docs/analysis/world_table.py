"""Is the world hard enough to rank controllers? straight / ORCA / the shipped policy in every scenario, in the
default world (attention) and in the old world of always-attentive humans (configs/env/reactive_humans.yaml).

    python docs/analysis/world_table.py --episodes 200 --seed 0

Prints one Markdown table: Goal / Collision / Time-out %, PV (intrusion events per 200 episodes) and the mean
disturbance per episode (sum over steps and nearby humans of |v_i - v_i^without robot| / v_pref_i), the quantity
the reward's disturbance term weights: how far the robot pushes people off their way.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import socnav
from socnav.controllers import make_controller
from socnav.envs.rollout import rollout_episodes, summarize

SCENARIOS = ("circle_crossing", "circle_interaction", "random", "position_swap")
WORLDS = {"default": {}, "old (reactive_humans.yaml)": "configs/env/reactive_humans.yaml"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--model", default="pretrained", help="learned policy to include ('' to skip)")
    args = parser.parse_args()
    root = Path(__file__).resolve().parents[2]
    learned = socnav.load_policy(args.model) if args.model else None
    print("| world | scenario | controller | Goal % | Collision % | Time-out % | PV | disturbance |")
    print("|:--|:--|:--|--:|--:|--:|--:|--:|")
    for world, base in WORLDS.items():
        for scenario in SCENARIOS:
            source = str(root / base) if isinstance(base, str) else base
            config = socnav.load_config(source, scenario=scenario)
            controllers = {name: make_controller(name, config) for name in ("straight", "orca")}
            if learned is not None:
                controllers["shipped policy"] = learned
            for name, controller in controllers.items():
                records = rollout_episodes(controller, config, args.episodes, seed=args.seed, n_envs=50)
                s = summarize(records)
                print(f"| {world} | {scenario} | {name} | {s['goal_pct']:.1f} | {s['collision_pct']:.1f} | "
                      f"{s['timeout_pct']:.1f} | {s['pv']:.0f} | {records['disturbance'].mean():.2f} |", flush=True)


if __name__ == "__main__":
    main()
