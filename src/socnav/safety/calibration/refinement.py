"""Stage 3 of the calibration: the refinement, a measured hill-climb from the rule stage 2 chose towards eager
neighbours, kept only where the replays say it prevents strictly more within the budget.

The proxy counts a rule's firing on the plain policy's steps, but the fallback steers the robot out of the
situations that made it fire, so the MEASURED false activation of the chosen rule is often well below the budget;
the refinement spends that margin where real rollouts say it prevents more. A longer hold of the fallback
(``Thresholds.hold_steps``) is one of the eager moves: only replays can score a hold.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import pandas as pd

from socnav.safety.calibration.proxy_search import SEARCHED_KEYS
from socnav.safety.calibration.rollout_selection import CalibrationRun, select_by_rollouts
from socnav.safety.rule import Thresholds

__all__ = [
    "REFINE_BETA_STEP",
    "REFINE_HOLD_STEP",
    "REFINE_PASSES",
    "REFINE_PROX_FACTOR",
    "REFINE_ROUNDS",
    "REFINE_UNCERTAINTY_FACTOR",
    "eager_neighbours",
    "refine_by_rollouts",
]

#: Rounds of the measured refinement around the chosen rule (stage 3 of `calibrate_thresholds`).
REFINE_ROUNDS = 3
#: Eager moves of the refinement: c_prox's threshold times this, beta1 plus this (seconds, closing-speed reading
#: only), each finite uncertainty threshold times this, the fallback's hold plus this (steps).
REFINE_PROX_FACTOR, REFINE_BETA_STEP, REFINE_UNCERTAINTY_FACTOR, REFINE_HOLD_STEP = 1.5, 0.5, 0.75, 1
#: Replays per refinement round at most: the current rule and its (at most 5) eager neighbours.
REFINE_PASSES = 6


def eager_neighbours(thresholds: Thresholds) -> list[Thresholds]:
    """Rules whose fallback drives wherever that of ``thresholds`` does and in more situations (for a longer
    look-ahead: wherever the gap is not growing), one parameter at a time: a larger
    ``lambda_prox`` (x :data:`REFINE_PROX_FACTOR`), for the ``closing-speed`` reading a longer look-ahead
    ``beta1`` (+ :data:`REFINE_BETA_STEP` s; with ``abs-relative-speed`` a larger beta1 fires LESS), each
    finite uncertainty threshold lower (x :data:`REFINE_UNCERTAINTY_FACTOR`), and a longer hold of the fallback
    (``hold_steps`` + :data:`REFINE_HOLD_STEP`; `socnav.safety.rule.held_fallback`). Only parameters the rule
    variant reads move (``thresholds.conditions``, :data:`SEARCHED_KEYS`): a proximity-only rule's uncertainty
    thresholds and an uncertainty-only rule's ``lambda_prox`` and ``beta1`` stay as they are."""
    t = thresholds
    searched = SEARCHED_KEYS[t.conditions]
    moves: list[dict[str, Any]] = []
    if "lambda_prox" in searched:
        moves.append({"lambda_prox": min(1000.0, max(t.lambda_prox * REFINE_PROX_FACTOR, t.lambda_prox + 0.1))})
        if t.proximity == "closing-speed":
            moves.append({"beta1": min(100.0, t.beta1 + REFINE_BETA_STEP)})
    for key in ("lambda_ep", "lambda_feat"):
        if key in searched and math.isfinite(getattr(t, key)) and getattr(t, key) > 0:
            moves.append({key: getattr(t, key) * REFINE_UNCERTAINTY_FACTOR})
    moves.append({"hold_steps": min(1000, t.hold_steps + REFINE_HOLD_STEP)})
    neighbours = [t.model_copy(update=move) for move in moves]
    return [n for n in neighbours if n != t]


def refine_by_rollouts(thresholds: Thresholds, table: pd.DataFrame, plain_collisions: Mapping[str, int],
                       policy: Any, estimator: Any, runs: Sequence[CalibrationRun], budget: float, window: int,
                       n_envs: int, confidence: float, progress: Callable[[int], None],
                       cache: dict[Thresholds, dict[str, Any]] | None = None) -> tuple[Thresholds, pd.DataFrame]:
    """Stage 3: up to :data:`REFINE_ROUNDS` rounds of measured hill-climbing from the chosen rule ``thresholds``
    towards eager ones (:func:`eager_neighbours`), each round replaying the current rule and its untried
    neighbours with `select_by_rollouts` (``plain_collisions``: the plain policy's, measured once in stage 2;
    ``cache``: the replays already played, see there). A neighbour replaces the current rule only if it prevents
    STRICTLY more (worst type, then mean): a more eager rule that merely ties is not worth its extra activations.

    :param table: stage 2's candidates table (``select_by_rollouts``, with a ``stage`` column); its rules are not
        tried again.
    :return: ``(thresholds, table)``: the rule kept and the table extended by every rule tried; every row has a
        ``stage`` (``refine-1``, ...) and a unique ``candidate`` number, and one row stays ``chosen``.
    """
    if thresholds == Thresholds.never():
        return thresholds, table
    # a paper rule's rows have no `conditions` column (its dump leaves the default out): it reads as the default
    fields = [key for key in Thresholds.model_fields if key in table]
    tried = {Thresholds.create(row) for row in table[fields].to_dict(orient="records")}
    for round_index in range(REFINE_ROUNDS):
        neighbours = [n for n in eager_neighbours(thresholds) if n not in tried]
        if not neighbours:
            break
        tried.update(neighbours)
        choice, round_table = select_by_rollouts([thresholds, *neighbours], policy, estimator, runs, budget, window,
                                                 n_envs, confidence, progress=progress,
                                                 plain_collisions=plain_collisions, cache=cache)
        score = ["prevented_worst", "prevented_fraction"]
        current = tuple(round_table.loc[0, score])
        best = tuple(round_table.loc[round_table["chosen"], score].iloc[0]) if round_table["chosen"].any() else None
        improved = choice != Thresholds.never() and best is not None and best > current
        tried_now = round_table.iloc[1:]  # row 0: the current rule, already in `table`
        round_table = tried_now.assign(stage=f"refine-{round_index + 1}",
                                       candidate=tried_now["candidate"] + len(table) - 1)
        if not improved:
            table = pd.concat([table, round_table.assign(chosen=False)], ignore_index=True)
            break
        table = pd.concat([table.assign(chosen=False), round_table], ignore_index=True)
        assert isinstance(choice, Thresholds)  # the rule's candidates give the rule's choice
        thresholds = choice
    return thresholds, table
