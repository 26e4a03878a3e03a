"""Safe action selection (paper IV-C): a probability-of-collision rule on the windowed
uncertainty and the nearest human, and a cautious ORCA controller that takes over when it fires.

The rule's thresholds are the paper's (:data:`THRESHOLD_PRESETS`) or calibrated from rollouts by
:func:`calibrate_thresholds` (``socnav.safety.calibration``: records, proxy search, selection by rollouts,
refinement).

Example::

    from socnav.safety import SafePolicy, Thresholds
    from socnav.uncertainty import MCDropoutEstimator

    safe = SafePolicy(policy, MCDropoutEstimator(policy, k=20, p_test=0.5), Thresholds.preset("mc"), config)
    actions, _ = safe.predict(obs)             # batched; safe.last_fallback says where the fallback acted
    safe.reset(done_envs)                      # at episode boundaries (or pass episode_start to predict)
"""

from socnav.safety.calibration import (
    RECORD_COLUMNS,
    CalibrationRun,
    ProxySearchResult,
    calibrate_budgets,
    calibrate_thresholds,
    collect_records,
    proxy_scores,
    rollout_scores,
    save_calibration,
    select_by_proxy,
    select_by_rollouts,
)
from socnav.safety.cautious import CAUTIOUS_RADIUS_SCALE, CautiousController
from socnav.safety.rule import (
    PROXIMITY_VARIANTS,
    RULE_CONDITIONS,
    SENSING_CHOICES,
    THRESHOLD_PRESETS,
    NearestHuman,
    RuleConditions,
    Thresholds,
    ThresholdsError,
    collision_probability,
    held_fallback,
    load_thresholds,
    nearest_human,
    proximity_score,
    rule_conditions,
    save_thresholds,
    shipped_layers,
)
from socnav.safety.safe_policy import FallbackCounter, SafePolicy, fallback_percent, no_uncertainty

# The built-in triggers defined in modules of their own register on import: every user of the registry finds them.
from socnav.safety import conformal, risk_model  # noqa: F401  isort: skip

__all__ = [
    "CAUTIOUS_RADIUS_SCALE",
    "PROXIMITY_VARIANTS",
    "RECORD_COLUMNS",
    "RULE_CONDITIONS",
    "SENSING_CHOICES",
    "THRESHOLD_PRESETS",
    "CalibrationRun",
    "CautiousController",
    "FallbackCounter",
    "NearestHuman",
    "ProxySearchResult",
    "RuleConditions",
    "SafePolicy",
    "Thresholds",
    "ThresholdsError",
    "calibrate_budgets",
    "calibrate_thresholds",
    "collect_records",
    "collision_probability",
    "fallback_percent",
    "held_fallback",
    "load_thresholds",
    "nearest_human",
    "no_uncertainty",
    "proximity_score",
    "proxy_scores",
    "rollout_scores",
    "rule_conditions",
    "save_calibration",
    "save_thresholds",
    "select_by_proxy",
    "select_by_rollouts",
    "shipped_layers",
]
