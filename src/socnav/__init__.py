"""socnav: uncertainty-aware social robot navigation with deep reinforcement learning.

A batched crowd simulator with socially individual ORCA humans, Gymnasium / SB3 environments and ODV-PPO.
"""

from socnav.config import ConfigError, EnvConfig, load_config
from socnav.envs import SocialNavEnv, SocialNavVecEnv, make_env, make_vec_env
from socnav.envs.registration import register_envs

__version__ = "0.1.0"
__all__ = [
    "ConfigError", "EnvConfig", "SocialNavEnv", "SocialNavVecEnv", "load_config", "load_policy", "make_env",
    "make_vec_env",
]


def __getattr__(name: str):
    # torch and SB3 load only when a learned policy is asked for: `import socnav` stays fast for simulation users.
    if name == "load_policy":
        from socnav.rl.persistence import load_policy

        return load_policy
    raise AttributeError(f"module 'socnav' has no attribute {name!r}")

register_envs()
