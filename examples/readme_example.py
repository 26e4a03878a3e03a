"""The README's Python example ("In Python"), runnable as is: `python examples/readme_example.py`.

The shipped policy, without and with the uncertainty-aware safety layer, on the same 20 episodes with heading noise.
Kept small so that it finishes in well under a minute on a loaded 2-core machine (the safety layer draws K = 20
MC-dropout samples per step); `rollout_episodes` shows a progress bar in a terminal.
"""

import socnav
from socnav.envs.rollout import rollout_episodes, summarize
from socnav.safety import SafePolicy
from socnav.uncertainty import MCDropoutEstimator

config = socnav.load_config({"scenario": "position_swap", "n_humans": 1, "perturbation": {"heading_noise": 0.8}})
policy = socnav.load_policy("pretrained")                                  # the shipped open-plane policy
safe = SafePolicy(policy, MCDropoutEstimator(policy, k=20), "mc", config)  # + the uncertainty-aware safety layer
for name, actor in [("policy", policy), ("policy + safety layer", safe)]:
    records = rollout_episodes(actor, config, n_episodes=20, seed=0)       # the same 20 episodes, one row each
    print(name, summarize(records, metrics=["goal_pct", "collision_pct"]))
