"""From socnav's safe policy format to a full Stable-Baselines3 model, e.g. to fine-tune a trained policy.
:func:`to_sb3` rebuilds the ODVPPO of a policy file: its preset, hyperparameters and weights.

``PPO.load("model.zip")`` cannot read a socnav policy file (it holds JSON and tensors, no pickled SB3 objects, so
SB3 reports ``No data found in the saved file``). :func:`to_sb3` rebuilds the model instead: an
:class:`~socnav.rl.ODVPPO` (an SB3 ``PPO`` subclass) of the file's preset and hyperparameters, on an environment of
the file's env config unless one is given, with the policy weights loaded::

    from socnav.rl.convert import to_sb3

    model = to_sb3("runs/swap/model.zip")            # or "pretrained"
    model.learn(50_000)                              # fine-tune as any SB3 model
    model.save("runs/swap/sb3_model.zip")            # SB3's own (pickled) format: ODVPPO.load(...) reads it back

The optimizer state is not in a policy file, so fine-tuning starts with a fresh Adam state (training checkpoints,
``socnav train --resume``, keep it). `socnav convert MODEL --to-sb3 OUT.zip` does the same from the command line.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from socnav.rl.odv_ppo import ODVPPO

__all__ = ["to_sb3"]


def to_sb3(path: str | Path, env: Any = None, seed: int | None = None, n_envs: int = 16,
           tensorboard_log: str | None = None) -> ODVPPO:
    """An SB3 model (:class:`ODVPPO`) holding the weights of the socnav policy file `path` (or ``"pretrained"``).

    :param env: the environment to continue training on (SB3 VecEnv or Gymnasium env with socnav's observation
        space); None: ``socnav.make_vec_env`` of the file's env config with `n_envs` environments.
    :param seed: SB3 seed of the new model; None: the file's training seed.
    :raises PolicyLoadError: `path` is not a readable socnav policy.
    """
    from socnav.envs import make_vec_env
    from socnav.rl.persistence import load_policy
    from socnav.rl.presets import make_model

    policy = load_policy(path)
    metadata = policy.socnav_metadata
    if env is None:
        env = make_vec_env(metadata["env_config"], n_envs=n_envs)
    seed = int(metadata.get("seed", 0)) if seed is None else seed
    model = make_model(metadata["algo"], env, seed=seed, overrides=dict(metadata["algo_config"]),
                       tensorboard_log=tensorboard_log)
    model.policy.load_state_dict(policy.state_dict(), strict=True)
    return model
