"""Reinforcement learning for socnav: ODV-PPO with dropout on Stable-Baselines3 (paper IV-A, Fig. 3; docs/training.md).
Policy network (LSTM extractor, ODV actor, critic), the ODVPPO algorithm and the five named presets.
"""

from socnav.rl.extractor import HumanLSTMExtractor
from socnav.rl.odv_ppo import ODVPPO, variance_loss
from socnav.rl.policy import NonFiniteError, ODVActorCriticPolicy, check_finite
from socnav.rl.presets import ALGOS, PRESETS, AlgoConfig, large_batch_overrides, make_model, resolve_config

__all__ = [
    "ALGOS",
    "ODVPPO",
    "PRESETS",
    "AlgoConfig",
    "HumanLSTMExtractor",
    "NonFiniteError",
    "ODVActorCriticPolicy",
    "check_finite",
    "large_batch_overrides",
    "make_model",
    "resolve_config",
    "variance_loss",
]
