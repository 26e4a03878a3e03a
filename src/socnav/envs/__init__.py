"""Gymnasium and Stable-Baselines3 environments over the crowd simulator (docs/world.md), with the paper's
perturbations (Sec. V-A) and batched evaluation rollouts."""

from socnav.envs.env import SocialNavEnv, make_env

__all__ = ["SocialNavEnv", "SocialNavVecEnv", "make_env", "make_vec_env"]


def __getattr__(name: str):
    # The SB3 VecEnv imports SB3 (and torch): load it on first use so that the simulator stays torch-free.
    if name in ("SocialNavVecEnv", "make_vec_env"):
        from socnav.envs import vec_env

        return getattr(vec_env, name)
    raise AttributeError(f"module 'socnav.envs' has no attribute {name!r}")
