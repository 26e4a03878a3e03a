"""The simulated world's configuration, where the simulator is: `EnvConfig` and `load_config` (`env`), its
sections (`sections`: ORCA, layout, scan, planner, reward, perturbations; `humans`). The simulator's kernels
do not import it: they read a world through small protocols (`socnav.sim.scenarios.ScenarioSettings`,
`socnav.sim.humans.HumanSettings`); `socnav.sim.world` assembles a world from it.
"""

from socnav.sim.config.env import (
    ConfigLike,
    EnvConfig,
    describe_world,
    load_config,
    perturbation_text,
)
from socnav.sim.config.humans import (
    REPLAY_MAX_FILES,
    HumansConfig,
    ReplayConfig,
    SocialForceConfig,
)
from socnav.sim.config.sections import (
    LayoutConfig,
    OrcaConfig,
    PerturbationConfig,
    PlannerConfig,
    Range,
    RewardConfig,
    ScanConfig,
    Section,
    check_range,
)

__all__ = [
    "REPLAY_MAX_FILES",
    "ConfigLike",
    "EnvConfig",
    "HumansConfig",
    "LayoutConfig",
    "OrcaConfig",
    "PerturbationConfig",
    "PlannerConfig",
    "Range",
    "ReplayConfig",
    "RewardConfig",
    "ScanConfig",
    "Section",
    "SocialForceConfig",
    "check_range",
    "describe_world",
    "load_config",
    "perturbation_text",
]
