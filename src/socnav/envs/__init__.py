"""Gymnasium and Stable-Baselines3 environments over the crowd simulator (SPEC section 2)."""

from socnav.envs.env import SocialNavEnv, make_env
from socnav.envs.vec_env import SocialNavVecEnv, make_vec_env

__all__ = ["SocialNavEnv", "SocialNavVecEnv", "make_env", "make_vec_env"]
