"""One ODV-PPO-Drop policy for the four map scenarios (docs/maps.md, "Learning among walls"): trained on all of them
at once (`socnav.envs.mixed.MixedVecEnv`, 4 environments each) with the 72-beam scan, the route in the observation
and a collision penalty of 20; first without humans, then with the default crowd, saved every ``--chunk`` steps so
that a later session continues with ``--start``; evaluated per scenario.

    python docs/analysis/maps_policy.py --humans 0 --steps 300000 --out runs/maps/empty.zip
    python docs/analysis/maps_policy.py --start runs/maps/empty.zip --steps 2000000 --out runs/maps/crowd.zip
    python docs/analysis/maps_policy.py --evaluate maps=runs/maps/crowd.zip --episodes 200 --seed 0
    # smooth driving (docs/training.md): --action-change-penalty 0.05 on the crowd stage
    # the humans in the scan's frame (the robot's heading): --frame heading on the first stage
    # a supervised start (DRL-VO's), imitating the ORCA robot's successful episodes (50,000 of its steps per
    # world; the clone alone is saved as runs/maps/cloned_clone.zip), then PPO in the crowd, then more PPO:
    python docs/analysis/maps_policy.py --clone 50000 --steps 1000000 --out runs/maps/cloned.zip
    python docs/analysis/maps_policy.py --start runs/maps/cloned.zip --steps 1500000 --out runs/maps/cloned_2500k.zip
    # ablations of the clone: --scan-people (the scan sees the people), --frame heading, --dagger 3 (with --steps 0)
    # DAgger taught by the ORCA robot that turns to its subgoal when stopped (the best map policy so far):
    python docs/analysis/maps_policy.py --clone 50000 --dagger 12 --dagger-epochs 1 --steps 0 --teacher-turn goal \
        --out runs/maps/dagger12_turn.zip      # the policy: runs/maps/dagger12_turn_clone.zip
    # its ablations: --scan-encoding nearness, --teacher-turn velocity (the ORCA robot as it drives itself)
    # a long DAgger run across sessions: --rounds-dir DIR saves each round; the same command continues after the last
    # (runs started before --train-seeds existed continue with --train-seeds 0)
    python docs/analysis/maps_policy.py --clone 50000 --dagger 40 --dagger-epochs 1 --steps 0 --teacher-turn goal \
        --rounds-dir runs/maps/dagger_turn_rounds --out runs/maps/dagger40_turn.zip
    # DAgger 20 (both options, 20 rounds), then 12 more rounds from it, driven by the policy alone or inside the
    # safety layer (--driver-safety), and all of them evaluated inside the layer beside the ORCA robot and straight:
    python docs/analysis/maps_policy.py --clone 50000 --dagger 20 --dagger-epochs 1 --steps 0 --teacher-turn goal \
        --scan-encoding nearness --train-seeds 0 --out runs/maps_dagger20_near_turn/cloned.zip
    python docs/analysis/maps_policy.py --start runs/maps_dagger20_near_turn/cloned_clone.zip --clone 50000 \
        --clone-epochs 1 --dagger 12 --dagger-epochs 1 --steps 0 --teacher-turn goal \
        --rounds-dir runs/maps_safe/rounds_plain --out runs/maps_safe/plain.zip
    python docs/analysis/maps_policy.py --start runs/maps_dagger20_near_turn/cloned_clone.zip --clone 50000 \
        --clone-epochs 1 --dagger 12 --dagger-epochs 1 --steps 0 --teacher-turn goal \
        --driver-safety src/socnav/data/pretrained-ppo_time-to-collision.yaml \
        --rounds-dir runs/maps_safe/rounds_ttc --out runs/maps_safe/ttc.zip  # (run before the layer's wall stop)
    python docs/analysis/maps_policy.py --evaluate "DAgger 20=runs/maps_dagger20_near_turn/cloned_clone.zip" \
        "DAgger 20 + 12=runs/maps_safe/plain_clone.zip" "DAgger 20 + 12, layer driving=runs/maps_safe/ttc_clone.zip" \
        --safety src/socnav/data/pretrained-ppo_time-to-collision.yaml --episodes 200 --seed 0
    # the same inside a layer that acts only in the last two seconds before contact
    python docs/analysis/maps_policy.py --evaluate "DAgger 20=runs/maps_dagger20_near_turn/cloned_clone.zip" \
        --safety src/socnav/data/pretrained-maps_time-to-collision.yaml --episodes 200 --seed 0
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import binomtest

from socnav.config import load_config
from socnav.controllers import OrcaController, make_controller
from socnav.envs.mixed import MixedVecEnv
from socnav.envs.rollout import rollout_episodes
from socnav.envs.vec_env import SocialNavVecEnv
from socnav.rl.convert import to_sb3
from socnav.rl.imitation import Demonstrations, clone, collect_demonstrations, track_feature_range
from socnav.rl.persistence import load_policy, save_policy
from socnav.rl.presets import make_model
from socnav.rl.smoothing import SmoothnessPenalty
from socnav.safety.assembly import assemble_safe_policy
from socnav.safety.safe_policy import FallbackCounter, fallback_percent

SCENARIOS = ("corridor", "doorway", "intersection", "room")
#: What every world of the mixture shares besides its scenario (configs/env/doorway_route_collision20.yaml's).
WORLD = {"scan": {"beams": 72, "range": 8.0, "fov": 360}, "planner": {"observe": True}, "reward": {"collision": 20.0}}
ENVS_PER_WORLD = 4
FEATURE_RANGE_SEEDS = 9_000_000  # --feature-range's episodes: beyond the DAgger rounds' (100,000 seeds apart)


def worlds(humans: int | None, scan: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """The env config of each scenario; `humans`: humans per episode (None: the scenario's default crowd); `scan`:
    the scan's settings (None: WORLD's)."""
    return [{"scenario": name, **WORLD, **({} if scan is None else {"scan": scan}),
             **({} if humans is None else {"n_humans": humans})} for name in SCENARIOS]


def _scan_of(policy: Any) -> dict[str, Any]:
    """The scan settings of the world a saved policy was trained in (its observation)."""
    return dict(policy.socnav_metadata["env_config"]["scan"])


def _collect(model: Any, configs: list[dict[str, Any]], args: argparse.Namespace, seed: int,
             driver: Any = None) -> Demonstrations:
    """``--clone`` steps of the ORCA robot's labels in each world, the robot driven by it or by `driver` (inside the
    safety layer with ``--driver-safety``: the states the deployed navigator reaches)."""
    parts = []
    for index, config in enumerate(configs):
        world = SocialNavVecEnv(config, n_envs=16)
        world.seed(args.train_seeds + seed + 1000 * index)
        teacher = OrcaController(world.config, stopped_turn=args.teacher_turn)
        actor = driver
        if driver is not None and args.driver_safety is not None:
            actor = assemble_safe_policy(driver, str(args.driver_safety), world.config)
        parts.append(collect_demonstrations(world, teacher, args.clone, gamma=model.gamma, driver=actor))
    return Demonstrations.concatenate(parts)


def _round_file(directory: Path, round_: int) -> Path:
    return directory / f"round_{round_:03d}.zip"


def supervised_start(model: Any, configs: list[dict[str, Any]], args: argparse.Namespace,
                     metadata: dict[str, Any]) -> None:
    """Clone the ORCA robot with the planner (`socnav.rl.imitation`): ``--clone`` of its steps in each world (the
    training seeds), imitating the episodes that ended as ``--imitate`` says, value head fitted to all; then
    ``--dagger`` rounds in which the policy drives and the ORCA robot labels every state it reaches (all imitated,
    whatever the episode's end: the label is what the teacher would do there).

    With ``--rounds-dir`` the policy after each round is saved there, and a run that finds rounds saved continues
    after the last one: the labels of the rounds before are collected again (each round's driver is the policy
    saved after the round before it, acting deterministically on the same seeds: the same states), not re-fitted."""
    demonstrations = None
    imitate = None if args.imitate == "all" else {args.imitate}
    saved = -1
    if args.rounds_dir is not None:
        args.rounds_dir.mkdir(parents=True, exist_ok=True)
        while saved < args.dagger and _round_file(args.rounds_dir, saved + 1).exists():
            saved += 1
    for round_ in range(1 + args.dagger):
        started = time.monotonic()
        driver = None if round_ == 0 else model.policy
        if 0 < round_ <= saved + 1:  # collected again with the policy that drove this round the first time
            driver = load_policy(_round_file(args.rounds_dir, round_ - 1))
        part = _collect(model, configs, args, args.seed + 100_000 * round_, driver)
        if driver is not None:  # DAgger's labels are imitated whatever the driver's episode came to
            part.outcomes = np.char.add("driven_", part.outcomes)
            imitate = None if imitate is None else imitate | set(np.unique(part.outcomes).tolist())
        names, counts = np.unique(part.outcomes, return_counts=True)
        print(f"round {round_}: {len(part):,} labelled steps ({dict(zip(names.tolist(), counts.tolist(), strict=True))}"
              f"), {time.monotonic() - started:.0f} s", flush=True)
        demonstrations = part if demonstrations is None else Demonstrations.concatenate([demonstrations, part])
        if round_ <= saved:
            continue
        if round_ == saved + 1 and saved >= 0:
            model.policy.load_state_dict(load_policy(_round_file(args.rounds_dir, saved)).state_dict())
            print(f"continuing after round {saved} ({_round_file(args.rounds_dir, saved)})", flush=True)
        epochs = args.clone_epochs if round_ == 0 else args.dagger_epochs
        for epoch, losses in enumerate(clone(model.policy, demonstrations, epochs=epochs,
                                             seed=args.seed + round_, imitate=imitate)):
            print(f"clone epoch {epoch}: " + ", ".join(f"{key} {value:.3f}" for key, value in losses.items()),
                  flush=True)
        if args.rounds_dir is not None:
            save_policy(model.policy, _round_file(args.rounds_dir, round_), metadata)


def train(args: argparse.Namespace) -> None:
    start_policy = None if args.start is None else load_policy(args.start)
    start = None if start_policy is None else dict(start_policy.socnav_metadata)
    scan = {**WORLD["scan"], "people": args.scan_people} if start_policy is None else _scan_of(start_policy)
    configs = worlds(args.humans, scan)
    if args.collision_penalty is not None:  # the reward is not observed: a policy may continue under another
        configs = [{**config, "reward": {"collision": args.collision_penalty}} for config in configs]
    env: Any = MixedVecEnv(configs, ENVS_PER_WORLD)
    # the smoothing cost of docs/training.md ("Smooth driving"); None: the start policy's (0 for a fresh one)
    penalty = args.action_change_penalty
    if penalty is None:
        penalty = 0.0 if start is None else float(start["algo_config"].get("action_change_penalty", 0.0))
    if penalty:
        env = SmoothnessPenalty(env, action_change_penalty=penalty)
    if start is not None:
        model = to_sb3(args.start, env=env, seed=args.seed)
        metadata = start
    else:
        model = make_model("odv-ppo-drop", env, seed=args.seed,
                           overrides={"frame": args.frame, "scan_encoding": args.scan_encoding})
        metadata = {"algo": "odv-ppo-drop", "algo_config": model.algo_config, "seed": args.seed, "timesteps": 0}
    metadata["algo_config"] = {**metadata["algo_config"], "action_change_penalty": penalty}
    # the policy acts in any of the worlds; its file names the doorway (the export's walls, `training_world`)
    metadata.update(env_config=load_config(configs[SCENARIOS.index("doorway")]).model_dump(mode="json"))
    if args.clone:
        supervised_start(model, configs, args, metadata)
        save_policy(model.policy, args.out.with_name(f"{args.out.stem}_clone.zip"), metadata)
    started, done, base = time.monotonic(), 0, int(metadata.get("timesteps", 0))
    while done < args.steps:
        chunk = min(args.chunk, args.steps - done)
        model.learn(chunk, reset_num_timesteps=False)
        done += chunk
        metadata["timesteps"] = base + done
        save_policy(model.policy, args.out, metadata)
        print(f"{base + done:,} steps, {time.monotonic() - started:.0f} s -> {args.out}", flush=True)
    if args.feature_range:  # a policy trained by imitation has no feature range; PPO's rollouts track one
        env.seed(args.train_seeds + FEATURE_RANGE_SEEDS)
        track_feature_range(model.policy, env, args.feature_range)
        save_policy(model.policy, args.out, metadata)
        print(f"feature range over {args.feature_range:,} steps it drove -> {args.out}", flush=True)


def _rate(hits: int, n: int) -> str:
    """``p [low, high]`` in %, the 95 % Clopper-Pearson interval."""
    interval = binomtest(hits, n).proportion_ci(0.95, method="exact")
    return f"{100 * hits / n:.1f} [{100 * interval.low:.1f}, {100 * interval.high:.1f}]"


def evaluate(args: argparse.Namespace) -> None:
    """Per map scenario (the default crowd) and in the open plane's position swap and circle crossing: the ORCA
    robot (with the planner) and each policy on the same episodes; in the open plane also `pretrained-ppo`. With
    ``--safety TRIGGER`` each policy also drives inside the safety layer with that trigger (its row adds the share
    of steps the cautious fallback drove), and so do the ORCA robot and `straight` (drive at the goal, or along the
    route): the ablation that says what the layer does without a learned policy."""
    policies = {}
    for item in args.evaluate:
        label, _, path = item.rpartition("=")
        policies[label or path] = load_policy(path)
    open_plane = [{"scenario": name, **WORLD} for name in ("position_swap", "circle_crossing")]
    open_plane[0]["n_humans"] = 1  # the shipped policy's world
    summary: dict[str, dict[str, str]] = {}  # controller -> scenario -> "goal / people / walls (fallback %)"
    print("| scenario | controller | Goal % [95 % CI] | people % [95 % CI] | wall % [95 % CI] | time-out % "
          "| jerk x ORCA | path irregularity x ORCA |")
    print("|:--|:--|--:|--:|--:|--:|--:|--:|")
    for config in [*worlds(None), *open_plane]:
        if args.scenarios and config["scenario"] not in args.scenarios:
            continue
        world = load_config(config)
        actors = {"ORCA robot": make_controller("orca", world), **policies}
        if not world.obstacles and world.scenario in ("position_swap", "circle_crossing"):
            actors["pretrained-ppo (open plane)"] = load_policy("pretrained-ppo")  # the PPO policy of docs/maps.md
        # each policy in the world it observes (with the scan it was trained with: the episodes are the same)
        rows = {label: rollout_episodes(actor, world if label not in policies else
                                        load_config({**config, "scan": _scan_of(actor)}),
                                        args.episodes, seed=args.seed, n_envs=50, progress=False)
                for label, actor in actors.items()}
        fallback = {}
        drivers = {"ORCA robot": (actors["ORCA robot"], world), "straight": (make_controller("straight", world), world),
                   **{label: (policy, load_config({**config, "scan": _scan_of(policy)}))
                      for label, policy in policies.items()}}
        for label, (policy, seen) in drivers.items() if args.safety is not None else ():
            safe = assemble_safe_policy(policy, str(args.safety), seen)
            counter = FallbackCounter(safe)
            records = rollout_episodes(safe, seen, args.episodes, seed=args.seed, n_envs=50, progress=False,
                                       observer=counter)
            rows[f"{label} + safety"] = records.assign(**counter.columns(records["episode"]))
            fallback[f"{label} + safety"] = f" (fallback {fallback_percent(rows[f'{label} + safety']):.0f} % of steps)"
        orca = rows["ORCA robot"]
        for label, records in rows.items():
            n, outcome = len(records), records["outcome"]
            summary.setdefault(label, {})[world.scenario] = (
                "{:g} / {:g} / {:g}".format(*(round(100 * float((outcome == name).mean()), 1)
                                              for name in ("goal", "collision", "collision_wall")))
                + (f" ({fallback_percent(records):.0f} %)" if label in fallback else ""))
            print(f"| {world.scenario} | {label}{fallback.get(label, '')} | "
                  f"{_rate(int((outcome == 'goal').sum()), n)} | "
                  f"{_rate(int((outcome == 'collision').sum()), n)} | "
                  f"{_rate(int((outcome == 'collision_wall').sum()), n)} | {100 * (outcome == 'timeout').mean():.1f} | "
                  f"{records['jerk_mean'].mean() / orca['jerk_mean'].mean():.1f} | "
                  f"{records['path_irregularity'].mean() / orca['path_irregularity'].mean():.1f} |", flush=True)
    # docs/maps.md's form: one row per controller, goal / people / walls in % per scenario, the fallback's share
    scenarios = list(dict.fromkeys(scenario for cells in summary.values() for scenario in cells))
    print("\n| controller | " + " | ".join(name.replace("_", " ") for name in scenarios) + " |")
    print("|:--|" + ":-:|" * len(scenarios))
    for label, cells in summary.items():
        print(f"| {label} | " + " | ".join(cells.get(name, "–") for name in scenarios) + " |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--start", type=Path, help="continue from this policy file")
    parser.add_argument("--humans", type=int, default=None, help="humans per episode (default: the crowd)")
    parser.add_argument("--steps", type=int, default=200_000)
    parser.add_argument("--chunk", type=int, default=250_000, help="steps between saves")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--clone", type=int, default=0, metavar="STEPS",
                        help="a fresh policy first imitates the ORCA robot for STEPS of its steps per world")
    parser.add_argument("--clone-epochs", type=int, default=10)
    parser.add_argument("--dagger", type=int, default=0, metavar="ROUNDS",
                        help="after cloning, ROUNDS in which the policy drives and the ORCA robot labels")
    parser.add_argument("--dagger-epochs", type=int, default=3, help="epochs over all labels after each round")
    parser.add_argument("--rounds-dir", type=Path, default=None,
                        help="save the policy after each DAgger round here; continue after the last round saved")
    parser.add_argument("--driver-safety", type=Path, default=None, metavar="TRIGGER",
                        help="in the DAgger rounds the policy drives inside the safety layer with this trigger file "
                             "(e.g. src/socnav/data/pretrained-ppo_time-to-collision.yaml)")
    parser.add_argument("--train-seeds", type=int, default=10_000_000, metavar="BASE",
                        help="the collections' seeds start here, far from the evaluation's (0-199) and the "
                             "validation's (100,000-100,199); runs before this option used 0")
    parser.add_argument("--teacher-turn", choices=("velocity", "goal", "goal-if-behind"), default="velocity",
                        help="how the ORCA teacher turns while a velocity behind it stops it (its stopped_turn)")
    parser.add_argument("--imitate", choices=("all", "goal"), default="goal",
                        help="which of the teacher's episodes are imitated (by how they ended)")
    parser.add_argument("--collision-penalty", type=float, default=None,
                        help="the reward's collision penalty (default: WORLD's, 20)")
    parser.add_argument("--scan-people", action="store_true",
                        help="a fresh policy's scan also sees the people (scan.people)")
    parser.add_argument("--frame", choices=("goal", "heading"), default="goal",
                        help="the frame the network reads the humans in (a fresh policy only; AlgoConfig.frame)")
    parser.add_argument("--scan-encoding", choices=("range", "nearness"), default="range",
                        help="what the scan encoder reads of each beam (a fresh policy only; AlgoConfig.scan_encoding)")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--feature-range", type=int, default=0, metavar="STEPS",
                        help="last, set the policy's feature range (feature uncertainty) over STEPS steps it drives "
                             "in the mixture and save it as --out (for a policy trained by imitation only)")
    parser.add_argument("--action-change-penalty", type=float, default=None,
                        help="smoothing cost per step (docs/training.md); default: the start policy's, else 0")
    parser.add_argument("--evaluate", nargs="+", metavar="[LABEL=]POLICY",
                        help="evaluate these policies in each scenario (and the open plane) instead")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--scenarios", nargs="+", default=None,
                        choices=(*SCENARIOS, "position_swap", "circle_crossing"),
                        help="with --evaluate: only these scenarios (default: the four map scenarios and the open plane's two)")
    parser.add_argument("--safety", type=Path, default=None, metavar="TRIGGER",
                        help="with --evaluate: also each policy inside the safety layer with this trigger file")
    args = parser.parse_args()
    if args.evaluate is not None:
        evaluate(args)
    else:
        if args.out is None:
            parser.error("--out is needed to train")
        train(args)


if __name__ == "__main__":
    main()
