"""Calibrating the safety rule's thresholds from rollouts (the paper tuned them by hand, paper V-B): records of
the plain policy, then three stages that each narrow the choice, chained by the workflow.

========================  ===================================================================================
module                    role
========================  ===================================================================================
``records``               per-step calibration records of the plain policy: columns, recorder, collection
``proxy_search``          stage 1: grid search over the thresholds scored by a proxy on the records
                          (:func:`select_by_proxy`), and the candidates it proposes (:func:`propose_candidates`)
``rollout_selection``     stage 2: replays of the calibration episodes with each candidate's SafePolicy, the
                          best within the false-activation budget kept (:func:`select_by_rollouts`)
``refinement``            stage 3: measured hill-climbing towards eager neighbours (:func:`refine_by_rollouts`)
``workflow``              the chain for one budget (:func:`calibrate_thresholds`, ``socnav calibrate``) or
                          several (:func:`calibrate_budgets`), and :func:`save_calibration`
========================  ===================================================================================

The proxy of stage 1 is optimistic (the cautious controller may still collide, or cause a later collision) and
the records come from the plain policy's trajectories, so stage 2 measures a few proxy candidates (e.g. one per
proximity reading and lead) in real rollouts, and stage 3 climbs from the choice only where the replays say a more
eager rule prevents strictly more within the budget. Every stage ranks rules by the perturbation type they handle
worst, then by the mean over types. The rule's ablations (``Thresholds.conditions``) go through the same stages,
each searching only the parameters it reads. Table 3 then evaluates the choice on held-out seeds and strengths
(docs/reproduction.md, Table 3).
"""

from socnav.safety.calibration.proxy_search import (
    CALIBRATION_LEADS,
    DEFAULT_BETA1_GRID,
    GRID_KEYS,
    NEUTRAL_VALUES,
    PROXY_BUDGET_SHARES,
    PROXY_HOLDS,
    SEARCHED_KEYS,
    ProxySearchResult,
    propose_candidates,
    proxy_scores,
    select_by_proxy,
)
from socnav.safety.calibration.records import (
    RECORD_COLUMNS,
    STEP_COLUMNS,
    CalibrationRecorder,
    collect_records,
    validate_records,
)
from socnav.safety.calibration.refinement import (
    REFINE_BETA_STEP,
    REFINE_HOLD_STEP,
    REFINE_PASSES,
    REFINE_PROX_FACTOR,
    REFINE_ROUNDS,
    REFINE_UNCERTAINTY_FACTOR,
    eager_neighbours,
    refine_by_rollouts,
)
from socnav.safety.calibration.rollout_selection import (
    CalibrationRun,
    clopper_pearson_upper,
    false_activation_upper,
    ratio_and_standard_error,
    rollout_scores,
    select_by_rollouts,
)
from socnav.safety.calibration.workflow import calibrate_budgets, calibrate_thresholds, save_calibration

__all__ = [
    "CALIBRATION_LEADS",
    "DEFAULT_BETA1_GRID",
    "GRID_KEYS",
    "NEUTRAL_VALUES",
    "PROXY_BUDGET_SHARES",
    "PROXY_HOLDS",
    "RECORD_COLUMNS",
    "REFINE_BETA_STEP",
    "REFINE_HOLD_STEP",
    "REFINE_PASSES",
    "REFINE_PROX_FACTOR",
    "REFINE_ROUNDS",
    "REFINE_UNCERTAINTY_FACTOR",
    "SEARCHED_KEYS",
    "STEP_COLUMNS",
    "CalibrationRecorder",
    "CalibrationRun",
    "ProxySearchResult",
    "calibrate_budgets",
    "calibrate_thresholds",
    "clopper_pearson_upper",
    "collect_records",
    "eager_neighbours",
    "false_activation_upper",
    "propose_candidates",
    "proxy_scores",
    "ratio_and_standard_error",
    "refine_by_rollouts",
    "rollout_scores",
    "save_calibration",
    "select_by_proxy",
    "select_by_rollouts",
    "validate_records",
]
