"""socnav: uncertainty-aware social robot navigation with deep reinforcement learning.

A batched crowd simulator with socially individual ORCA humans, Gymnasium / SB3 environments and ODV-PPO.
`import socnav` loads neither torch nor Stable-Baselines3: they load when a learned policy, the SB3 VecEnv or the
exporter is first asked for (so `socnav --help`, the simulator and the torch-free `socnav.runtime` stay light).
"""

from socnav.config import ConfigError, EnvConfig, load_config
from socnav.envs import SocialNavEnv, make_env
from socnav.envs.registration import register_envs

__version__ = "0.1.0"
__all__ = [
    "ConfigError", "EnvConfig", "SocialNavEnv", "SocialNavVecEnv", "export_onnx", "load_config", "load_policy",
    "make_env", "make_vec_env",
]

# name -> module that defines it; each loads torch/SB3 on first use only.
_LAZY = {
    "SocialNavVecEnv": "socnav.envs.vec_env",
    "make_vec_env": "socnav.envs.vec_env",
    "load_policy": "socnav.rl.persistence",
    "export_onnx": "socnav.export",
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'socnav' has no attribute {name!r}")


register_envs()
