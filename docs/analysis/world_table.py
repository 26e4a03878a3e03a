"""Is the world hard enough to rank controllers? straight / ORCA / a shipped policy in every scenario, in the
default world (attention) and in the world of always-attentive humans (configs/env/reactive_humans.yaml); with
``--humans``, in the default world with other human models (docs/humans.md), with Clopper-Pearson intervals.

    python docs/analysis/world_table.py --episodes 200 --seed 0
    python docs/analysis/world_table.py --episodes 200 --seed 0 --humans social_force mix \
        --scenarios circle_crossing circle_interaction
    python docs/analysis/world_table.py --episodes 200 --seed 0 --replay-files eth/*.txt   # recorded pedestrians
    python docs/analysis/world_table.py --episodes 200 --seed 0 --humans orca \
        --scenarios corridor doorway intersection room                                    # walls (docs/maps.md)

With ``--replay-files``, one table per recording (``scenario: replay``): the three controllers and a robot that stands
still at its start, the share of episodes in which pedestrians who ignore the robot walk into it anyway.

Prints one Markdown table: Goal / Collision / Time-out %, PV (intrusion events per 200 episodes) and the mean
disturbance per episode (sum over steps and nearby humans of |v_i - v_i^without robot| / v_pref_i), the quantity
the reward's disturbance term weights: how far the robot pushes people off their way.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import socnav
from socnav.controllers import make_controller
from socnav.envs.rollout import rollout_episodes, summarize

SCENARIOS = ("circle_crossing", "circle_interaction", "random", "position_swap")
MAP_SCENARIOS = ("corridor", "doorway", "intersection", "room")  # with walls (docs/maps.md), with --humans
WORLDS = {"default": {}, "reactive_humans.yaml": "configs/env/reactive_humans.yaml"}
#: --humans choices: the human models of the default world (mix: half ORCA, half social force, per human)
HUMAN_WORLDS = {"orca": {}, "social_force": {"humans": {"model": "social_force"}},
                "mix": {"humans": {"mix": {"orca": 0.5, "social_force": 0.5}}}}


def clopper_pearson(count: int, total: int, confidence: float = 0.95) -> str:
    """``p [low, high]`` in %, the exact binomial interval."""
    from scipy.stats import binomtest

    interval = binomtest(count, total).proportion_ci(confidence_level=confidence, method="exact")
    return f"{100 * count / total:.1f} [{100 * interval.low:.1f}, {100 * interval.high:.1f}]"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--model", default="pretrained", help="learned policy to include, named by this in the table ('' to skip)")
    parser.add_argument("--humans", nargs="+", choices=list(HUMAN_WORLDS),
                        help="human models of the default world to compare (with intervals) instead of the worlds")
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), choices=list(SCENARIOS) + list(MAP_SCENARIOS))
    parser.add_argument("--replay-files", nargs="+", metavar="FILE",
                        help="ETH/UCY-format recordings: the replay scenario, one recording at a time")
    args = parser.parse_args()
    root = Path(__file__).resolve().parents[2]
    learned = socnav.load_policy(args.model) if args.model else None
    if args.replay_files:
        replay_table(args, learned)
        return
    if args.humans:
        human_model_table(args, learned)
        return
    print("| world | scenario | controller | Goal % | Collision % | Time-out % | PV | disturbance |")
    print("|:--|:--|:--|--:|--:|--:|--:|--:|")
    for world, base in WORLDS.items():
        for scenario in args.scenarios:
            source = str(root / base) if isinstance(base, str) else base
            config = socnav.load_config(source, scenario=scenario)
            for name, records, s in played(config, learned, args):
                print(f"| {world} | {scenario} | {name} | {s['goal_pct']:.1f} | {s['collision_pct']:.1f} | "
                      f"{s['timeout_pct']:.1f} | {s['pv']:.0f} | {records['disturbance'].mean():.2f} |", flush=True)


class StandStill:
    """A robot that never moves (speed action -1): how often do people walk into a robot that does nothing?"""

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        return np.tile(np.array([[-1.0, 0.0]], dtype=np.float32), (len(observation["robot"]), 1)), None


def played(config: object, learned: object, args: argparse.Namespace, stand_still: bool = False):
    """(controller name, episode records, summary) of straight, ORCA, the learned policy and, if asked, a robot that
    stands still, in `config`."""
    controllers = {name: make_controller(name, config) for name in ("straight", "orca")}
    if learned is not None:
        controllers[args.model] = learned  # by its name: `pretrained`, `pretrained-ppo` or a file
    if stand_still:
        controllers["standing still"] = StandStill()
    for name, controller in controllers.items():
        records = rollout_episodes(controller, config, args.episodes, seed=args.seed, n_envs=50)
        yield name, records, summarize(records)


def human_model_table(args: argparse.Namespace, learned: object) -> None:
    """Goal and collision % with 95 % Clopper-Pearson intervals per human model, scenario and controller."""
    walls = any(scenario in MAP_SCENARIOS for scenario in args.scenarios)
    wall_header = " Wall collision % [95 % CI] |" if walls else ""
    print(f"| humans | scenario | controller | Goal % [95 % CI] | Collision % [95 % CI] |{wall_header} Time-out % | PV "
          "| disturbance |")
    print("|:--|:--|:--|--:|--:|" + ("--:|" if walls else "") + "--:|--:|--:|")
    for humans in args.humans:
        for scenario in args.scenarios:
            config = socnav.load_config({**HUMAN_WORLDS[humans], "scenario": scenario})
            for name, records, s in played(config, learned, args):
                goals, collisions, wall_hits = (int((records["outcome"] == outcome).sum())
                                                for outcome in ("goal", "collision", "collision_wall"))
                wall_cell = f" {clopper_pearson(wall_hits, len(records))} |" if walls else ""
                print(f"| {humans} | {scenario} | {name} | {clopper_pearson(goals, len(records))} | "
                      f"{clopper_pearson(collisions, len(records))} |{wall_cell} {s['timeout_pct']:.1f} | "
                      f"{s['pv']:.0f} | {records['disturbance'].mean():.2f} |", flush=True)


def replay_table(args: argparse.Namespace, learned: object) -> None:
    """Goal and collision % with 95 % Clopper-Pearson intervals per recording and controller, replayed humans."""
    print("| recording | controller | Goal % [95 % CI] | Collision % [95 % CI] | Time-out % | PV |")
    print("|:--|:--|--:|--:|--:|--:|")
    for path in args.replay_files:
        config = socnav.load_config({"scenario": "replay", "humans": {"model": "replay", "replay": {"files": [path]}}})
        for name, records, s in played(config, learned, args, stand_still=True):
            goals, collisions = (int((records["outcome"] == outcome).sum()) for outcome in ("goal", "collision"))
            print(f"| {Path(path).name} | {name} | {clopper_pearson(goals, len(records))} | "
                  f"{clopper_pearson(collisions, len(records))} | {s['timeout_pct']:.1f} | {s['pv']:.0f} |", flush=True)


if __name__ == "__main__":
    main()
