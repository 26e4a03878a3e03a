"""Calibrating the rule's thresholds from rollouts (the paper tuned them by hand, paper V-B).

**Records** -- one row per step of calibration rollouts of the PLAIN policy (no fallback), a pandas DataFrame:

==================  ==========================================================================================
``episode``         episode id, unique over the whole frame (e.g. an int offset per perturbation)
``step``            step index in the episode (0-based); the row is the observation at that step and the
                    action chosen from it
``perturbed``       bool: the episode ran in a perturbed world (the collisions to prevent) or not (the
                    false activations to avoid)
``u_ep_heading``    WINDOWED epistemic heading uncertainty at that step
``u_feat``          WINDOWED predictive feature uncertainty
``gap``             nearest-human gap ``d(t)`` from the sensed observation (``inf`` without humans)
``relative_speed``  ``|dv|`` to the nearest human
``previous_gap``    ``d(t-1)`` of the same episode, NaN at its first step
``collided``        per episode (repeated on its rows): the episode ended in a collision
``collision_step``  per episode: the ``step`` whose action led to the collision (its last step); NaN if none
``closing_speed``   optional: needed for ``proximity="closing-speed"``
``group``           optional: the perturbation type of a perturbed episode (its collisions are scored per type)
==================  ==========================================================================================

:func:`collect_records` produces this frame from rollouts.

**Objective -- a documented proxy.** Whether the fallback would have prevented a collision cannot be known
without re-running the episode with it. We count a collision of a perturbed episode as *preventable* if the rule
would have fired at one of the last ``lookback`` steps up to and including ``collision_step`` (default 4 steps =
1 s at dt = 0.25 s), or, with ``lead > 0``, up to ``collision_step - lead`` only (firing at the contact step
itself is too late when a human closes fast). :func:`calibrate` chooses ``(lambda_ep, lambda_feat, lambda_prox,
beta1)`` maximising the fraction of perturbed-episode collisions flagged so, subject to the fallback-activation rate -- the fraction of
steps of UNPERTURBED episodes where the rule fires -- being at most ``false_activation_budget``. Ties go to the
lowest activation rate, then to the least eager rule (larger ``lambda_ep``, larger ``lambda_feat``, smaller
``lambda_prox``, smaller ``beta1``). ``inf`` for an uncertainty threshold means that condition is switched off.

**Per perturbation type, worst type first.** With a ``group`` column (the perturbation type of each perturbed
episode), the flagged fraction is computed per type and rules are ranked by the WORST type's fraction, then by the
mean over types (then as above). Pooled counts let the type with the most collisions decide (e.g. more humans,
hundreds of collisions, over faster humans, a dozen), and even an equal-weight mean trades one type for another: in
Table 3 two rules with the same mean (71 %) prevented 98.6 % / 22 % and 13 % / 94 % of the observation-noise /
faster-humans collisions. A safety layer is judged by the perturbation it handles worst, so the calibration
maximises that (max-min) and uses the mean only to break ties.

The proxy is optimistic (the cautious controller may still collide, or cause a later collision) and the records
come from the plain policy's trajectories. :func:`select_by_rollouts` is therefore the second stage: it replays the
calibration episodes with :class:`~socnav.safety.SafePolicy` for a few proxy candidates (e.g. one per proximity
reading and lead) and keeps the one that prevents the most collisions (worst perturbation type, then the mean
over types) among those
whose false-activation rate is within the budget at a one-sided upper confidence bound, both measured. Table 3
then evaluates the choice on held-out seeds and strengths (docs/reproduction.md, Table 3). A third stage
(``_refine`` in :func:`calibrate_thresholds`) climbs from the choice towards eager neighbours
(:func:`eager_neighbours`), keeping a neighbour only if the replays say it prevents strictly more within the budget. The proxy scores the per-step rule
(``hold_steps = 0``): a hold of the fallback (``Thresholds.hold_steps``) changes the trajectories it is meant to
change, so only replays can score it: the second stage replays every proposed rule with and without a hold
(``PROXY_HOLDS``), and the third stage tries longer ones.

The search is an exhaustive, deterministic grid: quantile-based candidates (midpoints between distinct quantiles
of the records, over all rows and over the collision-window rows, so resolution is where it matters) for the
three lambdas and a fixed ``beta1`` list, or explicit candidate lists given in ``grid``. All
``lambda_ep`` x ``lambda_feat`` pairs of one ``(beta1, lambda_prox)`` are scored at once with 2-D cumulative
histograms, so large grids are cheap.

**Rule variants and budgets.** The same three stages calibrate the rule's ablations (``Thresholds.conditions``:
``proximity-only``, ``uncertainty-only``), each searching only the parameters it reads (:data:`SEARCHED_KEYS`; the
others get :data:`NEUTRAL_VALUES`), so every variant is chosen under the same false-activation budget on the same
calibration episodes. :func:`calibrate_budgets` chooses thresholds for several budgets at once (a trade-off curve):
the records and every replay are played once and shared, a candidate proposed for two budgets is scored once.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from statistics import NormalDist
from typing import Any

import numpy as np
import pandas as pd

from socnav.config import ConfigLike, load_config
from socnav.envs.perturbations import CALIBRATION_SEED, CALIBRATION_SET, is_perturbed, perturbed_config
from socnav.io import write_text_atomic
from socnav.safety.rule import (
    PROXIMITY_VARIANTS,
    RULE_CONDITIONS,
    Conditions,
    Proximity,
    Thresholds,
    _check_proximity,
    proximity_score,
    rule_conditions,
    save_thresholds,
)

__all__ = [
    "CALIBRATION_LEADS",
    "DEFAULT_BETA1_GRID",
    "NEUTRAL_VALUES",
    "PROXY_BUDGET_SHARES",
    "RECORD_COLUMNS",
    "SEARCHED_KEYS",
    "CalibrationRecorder",
    "CalibrationResult",
    "CalibrationRun",
    "calibrate",
    "calibrate_budgets",
    "calibrate_thresholds",
    "clopper_pearson_upper",
    "collect_records",
    "evaluate_thresholds",
    "rollout_scores",
    "save_calibration",
    "select_by_rollouts",
]

RECORD_COLUMNS = ("episode", "step", "perturbed", "u_ep_heading", "u_feat", "gap", "relative_speed",
                  "previous_gap", "collided", "collision_step")
DEFAULT_BETA1_GRID = (0.0, 0.25, 0.5, 1.0, 2.0)
GRID_KEYS = ("lambda_ep", "lambda_feat", "lambda_prox", "beta1")
#: The parameters each rule variant (`Thresholds.conditions`) reads, i.e. the ones its calibration searches.
SEARCHED_KEYS: dict[str, tuple[str, ...]] = {"paper": GRID_KEYS, "proximity-only": ("lambda_prox", "beta1"),
                                              "uncertainty-only": ("lambda_ep", "lambda_feat")}
#: What the calibration writes for the parameters of a removed condition (ignored by that rule): the values under
#: which the removed condition (nearly) always holds in eq. (10) -- any uncertainty above 0, any human within 1 km.
NEUTRAL_VALUES: dict[str, float] = {"lambda_ep": 0.0, "lambda_feat": 0.0, "lambda_prox": 1000.0, "beta1": 0.0}
#: Per-step columns a :class:`CalibrationRecorder` keeps (the per-episode ones are added by :func:`collect_records`).
STEP_COLUMNS = ("episode", "step", "u_ep_heading", "u_feat", "gap", "relative_speed", "closing_speed", "previous_gap")


@dataclass(frozen=True)
class CalibrationResult:
    """The chosen thresholds and their proxy scores on the calibration records.

    ``prevented_fraction``: fraction of perturbed-episode collisions flagged within ``lookback`` steps (proxy;
    with a ``group`` column the mean of the per-type fractions, ``worst_type_fraction`` their minimum);
    ``false_activation_rate``: fraction of unperturbed steps where the rule fires; ``frontier``: for every
    evaluated ``(beta1, lambda_prox)``, its best feasible ``(lambda_ep, lambda_feat)`` and scores.
    """

    thresholds: Thresholds
    prevented_fraction: float
    false_activation_rate: float
    n_collisions: int
    n_unperturbed_steps: int
    lookback: int
    false_activation_budget: float
    frontier: pd.DataFrame = field(repr=False)
    lead: int = 0
    worst_type_fraction: float = float("nan")


# ------------------------------------------------------------------------------------------------ helpers

def _speed_column(records: pd.DataFrame, proximity: Proximity) -> np.ndarray:
    _check_proximity(proximity)
    column = "relative_speed" if proximity == "abs-relative-speed" else "closing_speed"
    if column not in records:
        raise ValueError(f"records need a {column!r} column for proximity={proximity!r}")
    return records[column].to_numpy(np.float64)


def _validate(records: pd.DataFrame) -> pd.DataFrame:
    missing = [c for c in RECORD_COLUMNS if c not in records]
    if missing:
        raise ValueError(f"calibration records lack columns {missing}; required: {', '.join(RECORD_COLUMNS)}")
    per_episode = records.groupby("episode", sort=False)[["perturbed", "collided"]].nunique()
    if (per_episode > 1).any().any():
        raise ValueError("each episode id must have one 'perturbed' and one 'collided' value; are episode ids "
                         "unique across the perturbed and unperturbed rollouts?")
    return records.reset_index(drop=True)


def _window_rows(records: pd.DataFrame, lookback: int, lead: int = 0) -> np.ndarray:
    """Mask of the rows of perturbed collision episodes at steps ``collision_step - lookback < step <=
    collision_step - lead``: firing there leaves the fallback at least ``lead + 1`` actions before the contact."""
    collided = records["collided"].to_numpy(bool) & records["perturbed"].to_numpy(bool)
    step = records["step"].to_numpy(np.float64)
    end = records["collision_step"].to_numpy(np.float64)
    with np.errstate(invalid="ignore"):
        return collided & (step <= end - lead) & (step > end - lookback)


def _check_lead(lookback: int, lead: int) -> None:
    if lookback < 1:
        raise ValueError(f"lookback must be >= 1, got {lookback}")
    if not 0 <= lead < lookback:
        raise ValueError(f"lead must be in [0, lookback - 1] = [0, {lookback - 1}], got {lead}")


def _candidates(values: np.ndarray, focus: np.ndarray, n_quantiles: int, add_inf: bool) -> np.ndarray:
    """Midpoints between distinct quantiles of `values` and of `focus` (finite, >= 0), plus inf if asked."""
    levels = np.linspace(0.0, 1.0, n_quantiles)
    points = []
    for data in (values, focus):
        data = data[np.isfinite(data)]
        if data.size:
            points.append(np.quantile(data, levels))
    points = np.unique(np.concatenate(points)) if points else np.zeros(0)
    candidates = (points[1:] + points[:-1]) / 2 if points.size > 1 else points
    candidates = candidates[candidates >= 0]
    if add_inf:
        candidates = np.append(candidates, np.inf)
    return np.unique(candidates)


def _explicit(grid: Mapping[str, Sequence[float]] | None, key: str) -> np.ndarray | None:
    if grid is None or key not in grid:
        return None
    values = np.unique(np.asarray(list(grid[key]), dtype=np.float64))
    if values.size == 0 or np.isnan(values).any() or (values < 0).any():
        raise ValueError(f"grid[{key!r}] must be a non-empty list of numbers >= 0, got {list(grid[key])}")
    return values


def _bins(values: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """k with: value > thresholds[a] (the condition holds) iff a < k. NaN never holds (k = 0)."""
    values = np.where(np.isnan(values), -np.inf, values)
    return np.searchsorted(thresholds, values, side="left")


def _collision_types(records: pd.DataFrame, perturbed: np.ndarray, episode_codes: np.ndarray,
                     collision_code: dict[int, int]) -> tuple[np.ndarray, list[int]]:
    """Perturbation type index of each collision episode with window rows (in ``collision_code`` order) and the
    number of collision episodes per type, all collisions counted; one type if ``records`` has no ``group``."""
    collided_rows = perturbed & records["collided"].to_numpy(bool)
    if "group" in records:
        labels = records["group"].astype(str).to_numpy()
    else:
        labels = np.full(len(records), "perturbed", dtype=object)
    episode_type = dict(zip(episode_codes[collided_rows], labels[collided_rows]))
    types = sorted(set(episode_type.values()))
    index = {name: i for i, name in enumerate(types)}
    counts = [0] * len(types)
    for name in episode_type.values():
        counts[index[name]] += 1
    of_window = np.zeros(len(collision_code), dtype=np.int64)
    for code, position in collision_code.items():
        of_window[position] = index[episode_type[code]]
    return of_window, counts


def _not_firing(k_ep: np.ndarray, k_feat: np.ndarray, n_ep: int, n_feat: int) -> np.ndarray:
    """(n_ep, n_feat) count of items with neither condition holding at (lambda_ep[a], lambda_feat[b])."""
    histogram = np.zeros((n_ep + 1, n_feat + 1), dtype=np.int64)
    np.add.at(histogram, (k_ep, k_feat), 1)
    return histogram.cumsum(axis=0).cumsum(axis=1)[:n_ep, :n_feat]


# ------------------------------------------------------------------------------------------------ scoring

def evaluate_thresholds(records: pd.DataFrame, thresholds: Thresholds, lookback: int = 4,
                        lead: int = 0) -> dict[str, float]:
    """The calibration proxy of given thresholds on records (via the rule itself): ``prevented_fraction`` (the mean
    of the per-type fractions with a ``group`` column), ``worst_type_fraction``, ``false_activation_rate``,
    ``n_collisions``, ``n_unperturbed_steps``. It scores the per-step rule: ``thresholds.hold_steps`` is ignored
    (a hold changes the trajectories the records come from; :func:`rollout_scores` measures it)."""
    _check_lead(lookback, lead)
    records = _validate(records)
    fire = rule_conditions(records["u_ep_heading"], records["u_feat"], records["gap"],
                           _speed_column(records, thresholds.proximity), records["previous_gap"], thresholds).p_col
    window = _window_rows(records, lookback, lead)
    perturbed = records["perturbed"].to_numpy(bool)
    collisions = records.loc[perturbed & records["collided"].to_numpy(bool), "episode"].unique()
    flagged = set(records.loc[window & fire, "episode"].unique())
    types = (records.loc[perturbed, ["episode", "group"]].drop_duplicates("episode").set_index("episode")["group"]
             if "group" in records else pd.Series("perturbed", index=collisions))
    per_type: dict[str, list[bool]] = {}
    for episode in collisions:
        per_type.setdefault(str(types[episode]), []).append(episode in flagged)
    fractions = [float(np.mean(hits)) for hits in per_type.values()]
    unperturbed = ~perturbed
    return {
        "prevented_fraction": float(np.mean(fractions)) if fractions else float("nan"),
        "worst_type_fraction": float(np.min(fractions)) if fractions else float("nan"),
        "false_activation_rate": float(fire[unperturbed].mean()) if unperturbed.any() else float("nan"),
        "n_collisions": len(collisions),
        "n_unperturbed_steps": int(unperturbed.sum()),
    }


def _prox_candidates(score: np.ndarray, approaching: np.ndarray, window: np.ndarray, n_quantiles: int) -> np.ndarray:
    """Quantile-based ``lambda_prox`` candidates from the proximity scores of rows where ``c_ap`` holds, plus one
    just above the largest collision-window score (a gate that lets every approaching window row through)."""
    relevant = approaching & np.isfinite(score)
    candidates = _candidates(score[relevant], score[window & relevant], n_quantiles, False)
    finite_window = score[window & relevant]
    if finite_window.size:
        top = float(finite_window.max())
        candidates = np.unique(np.append(candidates, top + max(1e-6, 1e-6 * abs(top))))
    return candidates[candidates >= 0]


class _GridScorer:
    """Scores all ``(lambda_ep, lambda_feat)`` pairs at once for one proximity gate (the rows where ``c_prox`` and
    ``c_ap`` hold), from the rows' uncertainty bins ``k_ep``, ``k_feat`` (:func:`_bins`) and 2-D cumulative
    histograms."""

    def __init__(self, records: pd.DataFrame, perturbed: np.ndarray, window: np.ndarray, k_ep: np.ndarray,
                 k_feat: np.ndarray, n_ep: int, n_feat: int) -> None:
        self.k_ep, self.k_feat, self.n_ep, self.n_feat = k_ep, k_feat, n_ep, n_feat
        self.unperturbed = ~perturbed
        self.n_unperturbed = int(self.unperturbed.sum())
        episode_codes = pd.factorize(records["episode"])[0]
        self.window_index = np.flatnonzero(window)
        collision_code = {code: i for i, code in enumerate(np.unique(episode_codes[self.window_index]))}
        self.window_episode = np.array([collision_code[c] for c in episode_codes[self.window_index]], dtype=np.int64)
        self.n_window_episodes = len(collision_code)
        # Collision episodes without rows in their window can never be flagged: they count as not flagged.
        self.type_of_window_episode, self.type_collisions = _collision_types(records, perturbed, episode_codes,
                                                                             collision_code)

    def score(self, gate: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(false_rate, worst, prevented)``, each (n_ep, n_feat): the false-activation rate and the worst type's
        and the mean flagged fraction of the rule ``(c_ep or c_feat) and gate``."""
        gated_unperturbed = gate & self.unperturbed
        quiet = _not_firing(self.k_ep[gated_unperturbed], self.k_feat[gated_unperturbed], self.n_ep, self.n_feat)
        false_rate = (int(gated_unperturbed.sum()) - quiet) / self.n_unperturbed
        # An episode is flagged at (a, b) iff one of its gated window rows has k_ep > a or k_feat > b, i.e. iff
        # its largest k_ep > a or its largest k_feat > b: one (max_ep, max_feat) item per episode.
        gated_window = gate[self.window_index]
        max_ep = np.zeros(self.n_window_episodes, dtype=np.int64)
        max_feat = np.zeros(self.n_window_episodes, dtype=np.int64)
        np.maximum.at(max_ep, self.window_episode[gated_window], self.k_ep[self.window_index][gated_window])
        np.maximum.at(max_feat, self.window_episode[gated_window], self.k_feat[self.window_index][gated_window])
        types = self.type_of_window_episode
        per_type = np.stack([
            1.0 - (_not_firing(max_ep[types == t], max_feat[types == t], self.n_ep, self.n_feat)
                   + (n_type - np.sum(types == t))) / n_type
            for t, n_type in enumerate(self.type_collisions)])
        return false_rate, per_type.min(axis=0), per_type.mean(axis=0)


def _best_feasible(false_rate: np.ndarray, worst: np.ndarray, prevented: np.ndarray,
                   budget: float) -> tuple[int, int] | None:
    """Grid index ``(a, b)`` of the best pair within the false-activation budget -- worst type's fraction, then
    mean, then lowest false rate, then least eager (larger ``lambda_ep``, then larger ``lambda_feat``) -- or None."""
    feasible = false_rate <= budget + 1e-12
    if not feasible.any():
        return None
    a, b = np.nonzero(feasible)  # row-major, the order of the masked arrays below
    order = np.lexsort((-b, -a, false_rate[feasible], -prevented[feasible], -worst[feasible]))
    return int(a[order[0]]), int(b[order[0]])


def _preference(row: Mapping[str, float]) -> tuple[float, ...]:
    """Sort key of a frontier row, best first: worst type, mean, false rate, then the least eager rule."""
    return (-row["worst_type_fraction"], -row["prevented_fraction"], row["false_activation_rate"],
            -row["lambda_ep"], -row["lambda_feat"], row["lambda_prox"], row["beta1"])


def _check_conditions(conditions: str) -> None:
    if conditions not in RULE_CONDITIONS:
        raise ValueError(f"unknown rule conditions {conditions!r}; allowed: {', '.join(RULE_CONDITIONS)}")


def calibrate(
    records: pd.DataFrame,
    false_activation_budget: float = 0.05,
    grid: Mapping[str, Sequence[float]] | None = None,
    lookback: int = 4,
    proximity: Proximity = "abs-relative-speed",
    n_quantiles: int = 41,
    lead: int = 0,
    conditions: Conditions = "paper",
) -> CalibrationResult:
    """Choose the rule's thresholds on calibration records (see the module docstring for the format and proxy).

    :param records: per-step records of perturbed and unperturbed rollouts of the plain policy.
    :param false_activation_budget: the most fallback activations allowed, as a fraction of unperturbed steps.
    :param grid: optional explicit candidates per key (``lambda_ep``, ``lambda_feat``, ``lambda_prox``,
        ``beta1``); the others are quantile-based (``beta1``: :data:`DEFAULT_BETA1_GRID`).
    :param lookback: a collision counts as prevented if the rule fired in its last ``lookback`` steps ...
    :param lead: ... but not in its last ``lead`` ones (0: up to and including the step of the collision).
    :param proximity: speed term of ``c_prox`` (kept fixed, not searched).
    :param n_quantiles: quantile levels per candidate grid.
    :param conditions: the rule variant (`Thresholds.conditions`): ``paper`` searches all four parameters,
        ``proximity-only`` only ``lambda_prox`` and ``beta1``, ``uncertainty-only`` only ``lambda_ep`` and
        ``lambda_feat`` (:data:`SEARCHED_KEYS`); the parameters of a removed condition get
        :data:`NEUTRAL_VALUES` (the rule ignores them) and a ``grid`` entry for one is an error.

    Deterministic. The result's scores are the proxy on these records; evaluate on held-out seeds with real
    :class:`~socnav.safety.SafePolicy` rollouts.
    """
    if not 0.0 <= false_activation_budget <= 1.0:
        raise ValueError(f"false_activation_budget must be in [0, 1], got {false_activation_budget}")
    _check_lead(lookback, lead)
    _check_conditions(conditions)
    searched = SEARCHED_KEYS[conditions]
    if grid is not None:
        unknown = set(grid) - set(GRID_KEYS)
        if unknown:
            raise ValueError(f"unknown grid keys {sorted(unknown)}; allowed: {', '.join(GRID_KEYS)}")
        ignored = sorted(set(grid) - set(searched))
        if ignored:
            raise ValueError(f"grid keys {ignored} are not searched for conditions={conditions!r} (the rule ignores "
                             f"them); allowed: {', '.join(searched)}")
    records = _validate(records)
    perturbed = records["perturbed"].to_numpy(bool)
    n_unperturbed = int((~perturbed).sum())
    if n_unperturbed == 0:
        raise ValueError("calibration records hold no unperturbed steps: the false-activation rate is undefined")
    window = _window_rows(records, lookback, lead)
    n_collisions = len(records.loc[perturbed & records["collided"].to_numpy(bool), "episode"].unique())
    if n_collisions == 0:
        raise ValueError("no collisions in the perturbed episodes of the records: nothing to calibrate for")

    u_ep = records["u_ep_heading"].to_numpy(np.float64)
    u_feat = records["u_feat"].to_numpy(np.float64)
    gap = records["gap"].to_numpy(np.float64)
    previous_gap = records["previous_gap"].to_numpy(np.float64)
    approaching = np.isnan(previous_gap) | (gap <= previous_gap)  # c_ap, as in the rule

    if "lambda_ep" in searched:
        lambda_ep = _explicit(grid, "lambda_ep")
        lambda_ep = _candidates(u_ep, u_ep[window], n_quantiles, True) if lambda_ep is None else lambda_ep
        lambda_feat = _explicit(grid, "lambda_feat")
        lambda_feat = _candidates(u_feat, u_feat[window], n_quantiles, True) if lambda_feat is None else lambda_feat
        k_ep, k_feat = _bins(u_ep, lambda_ep), _bins(u_feat, lambda_feat)
    else:  # proximity-only: one "uncertainty condition" that holds on every row (k = 1 > a = 0)
        lambda_ep, lambda_feat = np.array([NEUTRAL_VALUES["lambda_ep"]]), np.array([NEUTRAL_VALUES["lambda_feat"]])
        k_ep, k_feat = np.ones(len(records), dtype=np.int64), np.zeros(len(records), dtype=np.int64)
    scorer = _GridScorer(records, perturbed, window, k_ep, k_feat, len(lambda_ep), len(lambda_feat))
    if "lambda_prox" in searched:
        speed = _speed_column(records, proximity)
        betas = _explicit(grid, "beta1")
        betas = np.asarray(DEFAULT_BETA1_GRID) if betas is None else betas
    else:  # uncertainty-only: no c_prox, one gate (c_ap)
        speed, betas = np.zeros(len(records)), np.array([NEUTRAL_VALUES["beta1"]])
    fixed_prox = _explicit(grid, "lambda_prox")

    # The frontier: per (beta1, lambda_prox), the best (lambda_ep, lambda_feat) within the budget.
    frontier_rows: list[dict[str, Any]] = []
    for beta in betas:
        if "lambda_prox" in searched:
            score = proximity_score(gap, speed, float(beta), proximity)
            prox_candidates = (_prox_candidates(score, approaching, window, n_quantiles) if fixed_prox is None
                               else fixed_prox)
            if fixed_prox is None and conditions == "proximity-only":  # a gate that (almost) never opens: with no
                prox_candidates = np.unique(np.append(prox_candidates, 0.0))  # uncertainty grid, no inf to fall on
            gates = [(lam_prox, approaching & np.isfinite(gap) & (score < lam_prox)) for lam_prox in prox_candidates]
        else:
            gates = [(NEUTRAL_VALUES["lambda_prox"], approaching)]
        for lam_prox, gate in gates:
            false_rate, worst, prevented = scorer.score(gate)
            best = _best_feasible(false_rate, worst, prevented, false_activation_budget)
            if best is None:
                continue
            a, b = best
            frontier_rows.append({"beta1": float(beta), "lambda_prox": float(lam_prox),
                                  "lambda_ep": float(lambda_ep[a]), "lambda_feat": float(lambda_feat[b]),
                                  "prevented_fraction": float(prevented[a, b]),
                                  "worst_type_fraction": float(worst[a, b]),
                                  "false_activation_rate": float(false_rate[a, b])})
    frontier = pd.DataFrame(frontier_rows, columns=["beta1", "lambda_prox", "lambda_ep", "lambda_feat",
                                                    "prevented_fraction", "worst_type_fraction",
                                                    "false_activation_rate"])
    if not frontier_rows:  # only possible with an explicit grid without inf, or a rule without uncertainty condition
        raise ValueError("no candidate thresholds meet the false-activation budget; add inf to grid['lambda_ep'] "
                         "and grid['lambda_feat'], or (proximity-only) smaller grid['lambda_prox'] values, or raise "
                         "the budget")
    row = min(frontier_rows, key=_preference)  # the first of equals, as the frontier is ordered
    thresholds = Thresholds.create(lambda_ep=row["lambda_ep"], lambda_feat=row["lambda_feat"],
                                   lambda_prox=row["lambda_prox"], beta1=row["beta1"], proximity=proximity,
                                   conditions=conditions)
    return CalibrationResult(
        thresholds=thresholds,
        prevented_fraction=row["prevented_fraction"],
        false_activation_rate=row["false_activation_rate"],
        n_collisions=n_collisions,
        n_unperturbed_steps=n_unperturbed,
        lookback=lookback,
        false_activation_budget=false_activation_budget,
        frontier=frontier,
        lead=lead,
        worst_type_fraction=row["worst_type_fraction"],
    )


# ------------------------------------------------------------------------------------------------ collecting

class CalibrationRecorder:
    """Rollout observer (``socnav.envs.rollout.rollout_episodes(..., observer=...)``) keeping one calibration row
    per step: what ``probe`` -- the :class:`~socnav.safety.SafePolicy` the rollout plays -- computed for that step's
    action (windowed uncertainty, nearest human, previous gap), episode ids shifted by ``episode_offset``.

    :meth:`frame` returns the per-step columns of the records (module docstring); the per-episode ones come from
    the rollout's episode records (see :func:`collect_records`).
    """

    def __init__(self, probe: Any, episode_offset: int = 0) -> None:
        self.probe = probe
        self.episode_offset = episode_offset
        self.steps: np.ndarray | None = None  # step index of each environment's current episode
        self._columns: dict[str, list[np.ndarray]] = {key: [] for key in STEP_COLUMNS}

    def on_episode_start(self, envs: np.ndarray) -> None:
        if self.steps is None:  # the first call names every environment of the rollout
            self.steps = np.zeros(len(envs), dtype=np.int64)
        self.steps[envs] = 0

    def on_step(self, observation: Any, actions: Any, result: Any, episodes: np.ndarray) -> None:
        # Called after the world stepped but before any reset: `probe.last_*` still describe this step's action.
        live = episodes >= 0
        probe, nearest = self.probe, self.probe.last_nearest
        for key, values in (("episode", episodes + self.episode_offset), ("step", self.steps),
                            ("u_ep_heading", probe.last_uncertainty["u_ep_heading"]),
                            ("u_feat", probe.last_uncertainty["u_feat"]), ("gap", nearest.gap),
                            ("relative_speed", nearest.relative_speed), ("closing_speed", nearest.closing_speed),
                            ("previous_gap", probe.last_previous_gap)):
            self._columns[key].append(np.asarray(values)[live])
        self.steps += 1

    def frame(self) -> pd.DataFrame:
        """The recorded steps, in the order they were played (columns :data:`STEP_COLUMNS`)."""
        return pd.DataFrame({key: np.concatenate(values) for key, values in self._columns.items()})


def collect_records(
    policy: Any,
    estimator: Any,
    config: ConfigLike,
    n_episodes: int,
    seed: int = 0,
    perturbed: bool | None = None,
    window: int = 4,
    n_envs: int = 8,
    episode_offset: int = 0,
    deterministic: bool = True,
    progress: Callable[[int], None] | None = None,
    sensing: str = "perceived",
) -> pd.DataFrame:
    """Per-step calibration records (module docstring) of ``n_episodes`` plain-policy episodes (episode k from
    seed ``seed + k``, id ``episode_offset + k``), with the windowed uncertainty of ``estimator``.

    ``perturbed``: the flag to store; None: True iff the config has any registered perturbation type switched on
    (`socnav.envs.perturbations.is_perturbed`: every type of the registry compared with its unperturbed value).
    ``sensing``: what the proximity columns (``gap``, speeds, ``previous_gap``) are read from, as
    ``Thresholds.sensing``: the observation (``perceived``) or the noise-free state (``true``).
    ``progress(n)`` is called with the number of episodes finished at each step that finishes some.
    ``estimator`` None: no uncertainty is estimated (the columns hold 0), for a rule that reads none
    (``Thresholds.conditions == "proximity-only"``).
    Concatenate the frames of an unperturbed and some perturbed configs (distinct ``episode_offset``).
    """
    from socnav.envs.rollout import rollout_episodes
    from socnav.safety.safe_policy import SafePolicy, no_uncertainty

    config = load_config(config)
    if perturbed is None:
        perturbed = is_perturbed(config)
    # A SafePolicy whose rule never fires plays exactly `policy` and computes the rule's inputs on the way.
    probe = SafePolicy(policy, no_uncertainty if estimator is None else estimator,
                       Thresholds.create(Thresholds.never().model_dump(), sensing=sensing), config, window=window)
    recorder = CalibrationRecorder(probe, episode_offset)
    episodes = rollout_episodes(probe, config, n_episodes, seed=seed, n_envs=n_envs, deterministic=deterministic,
                                progress=progress, observer=recorder)
    episodes = episodes.set_index(episodes["episode"] + episode_offset)
    collided = episodes["outcome"] == "collision"
    frame = recorder.frame()
    frame["perturbed"] = bool(perturbed)
    frame["collided"] = frame["episode"].map(collided).astype(bool)
    # The action of an episode's last step is the one that led to its end.
    frame["collision_step"] = frame["episode"].map((episodes["length"] - 1).where(collided)).astype(np.float64)
    ordered = [*RECORD_COLUMNS, "closing_speed"]
    return frame[ordered].sort_values(["episode", "step"], ignore_index=True)


# ------------------------------------------------------------------------------------------------ validating

@dataclass(frozen=True)
class CalibrationRun:
    """One configuration of calibration episodes: ``n_episodes`` episodes, episode k from seed ``seed + k``;
    ``group`` names the perturbation type (runs of one type are pooled when scoring)."""

    config: Any
    perturbed: bool
    n_episodes: int
    seed: int
    group: str = "perturbed"


def _restart(estimator: Any) -> None:
    restart = getattr(estimator, "restart", None)
    if callable(restart):  # a seeded MC-dropout estimator: every candidate sees the same mask stream
        restart()


def rollout_scores(thresholds: Thresholds | None, policy: Any, estimator: Any, runs: Sequence[CalibrationRun],
                   window: int = 4, n_envs: int = 40,
                   progress: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Collisions and fallback activations of real rollouts on ``runs``: the plain ``policy`` if ``thresholds``
    is None, else :class:`~socnav.safety.SafePolicy` with them. ``progress(n)``: n more episodes finished.

    :return: ``collisions`` (dict group -> count over the perturbed runs' episodes of that group),
        ``false_activation_rate`` (fallback steps / steps over the unperturbed runs; 0 for the plain policy), its
        standard error ``false_activation_se``, and the counts ``false_activation_steps`` and ``unperturbed_steps``.
    """
    from socnav.envs.rollout import rollout_episodes
    from socnav.safety.safe_policy import FallbackCounter, SafePolicy

    collisions: dict[str, int] = {}
    lengths: list[np.ndarray] = []
    fallbacks_per_episode: list[np.ndarray] = []
    for run in runs:
        if thresholds is None:
            records = rollout_episodes(policy, run.config, run.n_episodes, seed=run.seed, n_envs=n_envs,
                                       progress=progress)
            fallbacks = np.zeros(len(records))
        else:
            _restart(estimator)
            safe = SafePolicy(policy, estimator, thresholds, run.config, window=window)
            counter = FallbackCounter(safe)
            records = rollout_episodes(safe, run.config, run.n_episodes, seed=run.seed, n_envs=n_envs,
                                       observer=counter, progress=progress)
            fallbacks = np.asarray(counter.per_episode(records["episode"]), dtype=np.float64)
        if run.perturbed:
            collisions[run.group] = collisions.get(run.group, 0) + int((records["outcome"] == "collision").sum())
        else:
            lengths.append(records["length"].to_numpy(np.float64))
            fallbacks_per_episode.append(fallbacks)
    counts = np.concatenate(fallbacks_per_episode) if fallbacks_per_episode else np.zeros(0)
    steps = np.concatenate(lengths) if lengths else np.zeros(0)
    rate, standard_error = _ratio_and_standard_error(counts, steps)
    return {"collisions": collisions, "false_activation_rate": rate, "false_activation_se": standard_error,
            "false_activation_steps": int(counts.sum()), "unperturbed_steps": int(steps.sum())}


def clopper_pearson_upper(events: int, trials: int, confidence: float = 0.95) -> float:
    """Exact (Clopper-Pearson) one-sided upper confidence bound of a binomial proportion after ``events`` in
    ``trials``: the p at which seeing at most ``events`` has probability ``1 - confidence``, i.e. the
    ``confidence`` quantile of Beta(events + 1, trials - events); 1 when every trial is an event. Unlike the
    normal approximation it is not 0 after 0 events: 1 - (1 - confidence)^(1 / trials), about 3 / trials at 95 %.
    """
    from scipy.stats import beta

    if trials < 1:
        return 1.0
    if not 0 <= events <= trials:
        raise ValueError(f"events must be in [0, trials={trials}], got {events}")
    if events == trials:
        return 1.0
    return float(beta.ppf(confidence, events + 1, trials - events))


def false_activation_upper(scores: Mapping[str, Any], confidence: float) -> float:
    """One-sided upper bound of a measured false-activation rate (``rollout_scores`` output): the larger of the
    normal bound ``rate + z SE`` with episodes as the independent units (wide when activations cluster in a few
    episodes) and the exact Clopper-Pearson bound on the step counts (not 0 when no step fired, where the normal
    bound collapses to the point estimate). ``confidence = 0.5``: the point estimate."""
    rate = float(scores["false_activation_rate"])
    if confidence <= 0.5:
        return rate
    normal = rate + NormalDist().inv_cdf(confidence) * float(scores["false_activation_se"])
    exact = clopper_pearson_upper(int(scores["false_activation_steps"]), int(scores["unperturbed_steps"]),
                                  confidence)
    return max(normal, exact)


def _ratio_and_standard_error(counts: np.ndarray, lengths: np.ndarray) -> tuple[float, float]:
    """Steps-weighted rate ``sum(counts) / sum(lengths)`` over episodes and its standard error, episodes being the
    independent units (steps of one episode are not): the ratio estimator's linearised variance,
    ``SE^2 = sum((c_i - r n_i)^2) / (m (m - 1) mean(n)^2)``."""
    m, total = len(lengths), float(lengths.sum())
    if m == 0 or total == 0:
        return float("nan"), float("nan")
    rate = float(counts.sum()) / total
    if m < 2:
        return rate, float("inf")
    residual = counts - rate * lengths
    return rate, float(np.sqrt((residual ** 2).sum() / (m * (m - 1))) / lengths.mean())


def select_by_rollouts(candidates: Sequence[Thresholds], policy: Any, estimator: Any,
                       runs: Sequence[CalibrationRun], false_activation_budget: float = 0.05, window: int = 4,
                       n_envs: int = 40, confidence: float = 0.95,
                       progress: Callable[[int], None] | None = None,
                       plain_collisions: Mapping[str, int] | None = None,
                       cache: dict[Thresholds, dict[str, Any]] | None = None) -> tuple[Thresholds, pd.DataFrame]:
    """The candidate that prevents the most collisions in REAL rollouts on the calibration ``runs``, among those
    whose measured false-activation rate (unperturbed runs) is within ``false_activation_budget`` with
    ``confidence``: its one-sided upper bound (:func:`false_activation_upper`: the larger of the normal bound
    ``rate + z * SE``, episodes as the independent units, and the exact Clopper-Pearson bound on the steps;
    ``confidence = 0.5`` uses the point estimate) must not exceed the budget. ``progress(n)``: n more episodes
    replayed (``len(candidates) + 1`` passes over ``runs``; ``len(candidates)`` with ``plain_collisions``). A few
    dozen calibration
    episodes estimate the rate only roughly; without the margin, a rule chosen at the edge of the budget can
    exceed it on new episodes.

    Per perturbation type (``CalibrationRun.group``) with plain-policy collisions, prevented fraction =
    (plain collisions - safe collisions) / plain collisions on the same episode seeds (a rule that causes
    collisions scores lower); candidates are ranked by the WORST type's fraction (``prevented_worst``), then by the
    MEAN over types (``prevented_fraction``), so that no perturbation type is traded for another (pooled counts
    would let the type with the most collisions decide; see the module docstring). Further ties go to the lower
    false-activation rate, then to the earlier candidate. If no candidate meets the budget, thresholds that never
    fire are returned (the layer is then off). Deterministic given a deterministic policy and a seeded estimator.

    ``plain_collisions``: the plain policy's collisions per type on these ``runs`` (``rollout_scores(None, ...)``'s
    ``collisions``) if already measured: the plain pass is then skipped. ``cache``: ``rollout_scores`` of
    candidates already replayed on these ``runs`` (thresholds -> scores), read and extended: a candidate found there
    is not replayed again (the replays are deterministic, so the numbers are the same).

    :return: ``(thresholds, table)``: one row per candidate with ``prevented_worst`` and ``prevented_fraction``
        (the score, lexicographically), one
        ``prevented_<group>`` column per type, ``false_activation_rate``, ``false_activation_upper`` and ``chosen``.
    """
    if not candidates:
        raise ValueError("select_by_rollouts needs at least one candidate")
    if not 0.5 <= confidence < 1.0:
        raise ValueError(f"confidence must be in [0.5, 1), got {confidence}")
    if not any(run.perturbed for run in runs) or all(run.perturbed for run in runs):
        raise ValueError("runs need both perturbed (collisions to prevent) and unperturbed (false activations) runs")
    if plain_collisions is not None:
        expected = {run.group for run in runs if run.perturbed}
        if set(plain_collisions) != expected:
            raise ValueError(f"plain_collisions has the perturbation types {sorted(plain_collisions)}, the runs "
                             f"{sorted(expected)}: measure them on these runs")
    plain = (dict(plain_collisions) if plain_collisions is not None
             else rollout_scores(None, policy, estimator, runs, window, n_envs, progress)["collisions"])
    groups = [group for group, count in plain.items() if count > 0]
    rows = []
    for index, thresholds in enumerate(candidates):
        if cache is not None and thresholds in cache:
            scores = cache[thresholds]
        else:
            scores = rollout_scores(thresholds, policy, estimator, runs, window, n_envs, progress)
            if cache is not None:
                cache[thresholds] = scores
        per_group = {group: (plain[group] - scores["collisions"][group]) / plain[group] for group in groups}
        rows.append({**thresholds.model_dump(), "candidate": index, "plain_collisions": sum(plain.values()),
                     "safe_collisions": sum(scores["collisions"].values()),
                     "prevented_fraction": float(np.mean(list(per_group.values()))) if groups else float("nan"),
                     "prevented_worst": float(np.min(list(per_group.values()))) if groups else float("nan"),
                     **{f"prevented_{group}": value for group, value in per_group.items()},
                     "false_activation_rate": scores["false_activation_rate"],
                     # A rule that cannot fire has no false activation to be uncertain about.
                     "false_activation_upper": (0.0 if thresholds == Thresholds.never()
                                                else false_activation_upper(scores, confidence))})
    table = pd.DataFrame(rows)
    table.attrs["plain_collisions"] = plain
    feasible = table["false_activation_upper"] <= false_activation_budget + 1e-12
    table["chosen"] = False
    if not feasible.any() or not groups:
        return Thresholds.never(), table
    ranked = table[feasible].sort_values(["prevented_worst", "prevented_fraction", "false_activation_rate",
                                          "candidate"], ascending=[False, False, True, True])
    best = int(ranked.index[0])
    table.loc[best, "chosen"] = True
    return candidates[best], table


# ------------------------------------------------------------------------------------------------ the workflow

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


#: Leads searched by the calibration proxy: the rule must fire at least this many steps before the collision step.
CALIBRATION_LEADS = (0, 1, 2)
#: The proxy search also runs at these fractions of the budget: candidates with a margin below it.
PROXY_BUDGET_SHARES = (1.0, 0.5)
#: Fallback holds (`Thresholds.hold_steps`) each proposed rule is replayed with in stage 2.
PROXY_HOLDS = (0, 1)


def _refine(thresholds: Thresholds, table: pd.DataFrame, plain_collisions: Mapping[str, int], policy: Any,
            estimator: Any, runs: Sequence[CalibrationRun], budget: float, window: int, n_envs: int,
            confidence: float, progress: Callable[[int], None],
            cache: dict[Thresholds, dict[str, Any]] | None = None) -> tuple[Thresholds, pd.DataFrame]:
    """Stage 3: up to :data:`REFINE_ROUNDS` rounds of measured hill-climbing from the chosen rule towards eager ones
    (:func:`eager_neighbours`), each round replaying the current rule and its untried neighbours with
    :func:`select_by_rollouts` (``plain_collisions``: the plain policy's, measured once in stage 2; ``cache``: the
    replays already played, see there). A neighbour
    replaces the current rule only if it prevents STRICTLY more (worst type, then mean): a more eager rule that
    merely ties is not worth its extra activations. The proxy counts a rule's firing on the plain policy's steps,
    but the fallback steers the robot out of the situations that made it fire, so the MEASURED false activation is
    often well below the budget; this spends that margin where real rollouts say it prevents more. Every row gets
    a ``stage`` and a unique ``candidate`` number; one row stays ``chosen``."""
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
        round_table = round_table.iloc[1:].assign(stage=f"refine-{round_index + 1}",  # row 0: the current rule
                                                  candidate=lambda frame: frame["candidate"] + len(table) - 1)
        if not improved:
            table = pd.concat([table, round_table.assign(chosen=False)], ignore_index=True)
            break
        table = pd.concat([table.assign(chosen=False), round_table], ignore_index=True)
        thresholds = choice
    return thresholds, table


def calibrate_thresholds(policy: Any, estimator: Any, env: dict[str, Any], episodes: int, budget: float = 0.05,
                         proximity: str = "both", window: int = 4, confidence: float = 0.95,
                         progress: Callable[[int, int], None] | None = None,
                         sensing: str = "perceived", conditions: str = "paper") -> tuple[Thresholds, dict[str, Any]]:
    """Thresholds chosen on calibration episodes: `episodes` unperturbed ones and `episodes` per strength of
    `CALIBRATION_SET`, from episode seeds `CALIBRATION_SEED`... (disjoint from the evaluation's). A perturbation
    type registered without calibration strengths (the behaviour shift) is held out: never played here.

    Three stages. (1) The proxy search (`socnav.safety.calibrate`) on per-step records of the plain policy proposes
    one candidate per proximity variant (`proximity`: one of `PROXIMITY_VARIANTS`, or `both`), lead in
    `CALIBRATION_LEADS` and proxy budget (`PROXY_BUDGET_SHARES` of `budget`): the proxy alone rewards a rule that
    fires at the very step of the contact, too late for the fallback when humans close fast, so candidates that
    must fire 1 or 2 steps earlier compete too. (2) `socnav.safety.select_by_rollouts` replays the same
    calibration episodes with each candidate's `SafePolicy`, each candidate once per fallback hold in `PROXY_HOLDS`
    (the proxy cannot score a hold), and keeps the one that prevents the most collisions
    (the worst perturbation type, then the mean over types) among those whose false-activation rate is within
    `budget` at `confidence` (one-sided upper bound), both MEASURED in those rollouts. (3) `_refine`: up to
    `REFINE_ROUNDS` rounds of measured hill-climbing towards eager neighbours of the chosen rule (`eager_neighbours`,
    a longer hold of the fallback among them), spending the margin between the proxy's and the measured false
    activation. Every stage scores per perturbation
    type, worst type first (`socnav.safety.calibration`): no type is traded for another. The report's
    ``candidates`` lists every rule tried with its ``stage`` (``proxy``, ``refine-1``, ...).

    `progress(done, total)`: episodes played so far and in all (the total shrinks once the number of distinct
    candidates is known; it starts at the most there can be).

    `sensing` (``perceived`` | ``true``, `socnav.safety.Thresholds.sensing`): what the rule's proximity terms and
    the fallback read, in the records and the replays alike; the thresholds returned carry it.

    `conditions` (`socnav.safety.Thresholds.conditions`): the rule variant calibrated -- eq. (10) (``paper``) or one
    of its ablations, each searching only the parameters it reads (`calibrate`, `eager_neighbours`); an
    ``uncertainty-only`` rule has no c_prox, so one proximity reading is enough. A ``proximity-only`` rule reads no
    uncertainty: `estimator` may then be None (nothing is estimated; much cheaper).

    Several budgets on the same episodes: `calibrate_budgets`.

    :return: ``(thresholds, report)``; without any collision to learn from, thresholds that never fire.
    """
    return calibrate_budgets(policy, estimator, env, episodes, [budget], proximity, window, confidence, progress,
                             sensing, conditions)[budget]


def calibrate_budgets(policy: Any, estimator: Any, env: dict[str, Any], episodes: int, budgets: Sequence[float],
                      proximity: str = "both", window: int = 4, confidence: float = 0.95,
                      progress: Callable[[int, int], None] | None = None, sensing: str = "perceived",
                      conditions: str = "paper",
                      light: Sequence[float] = ()) -> dict[float, tuple[Thresholds, dict[str, Any]]]:
    """`calibrate_thresholds` for each false-activation budget of `budgets` (a trade-off curve: prevented share vs
    false activation), on the same calibration episodes: the records, the plain policy's replay and every
    candidate's replay are played once and shared by all budgets (a candidate proposed for two budgets is scored
    once). Each budget's result is what `calibrate_thresholds` with that budget alone returns -- except for the
    budgets in `light`, chosen by a lighter search for the points of a trade-off curve (their reports say
    ``"search": "light"``): stage 1 at the budget itself only (not also at the other `PROXY_BUDGET_SHARES`) and with
    the c_prox reading(s) the other budgets chose (the reading is the rule's form, not a matter of budget), and no
    stage 3. Applied to every rule alike, it keeps their comparison at each budget fair at about half the replays.

    :return: budget -> ``(thresholds, report)``, in the order of `budgets`.
    """
    if proximity != "both" and proximity not in PROXIMITY_VARIANTS:
        raise ValueError(f"proximity must be one of: both, {', '.join(PROXIMITY_VARIANTS)}; got {proximity!r}")
    _check_conditions(conditions)
    budgets = [float(b) for b in budgets]
    if not budgets or any(not 0.0 <= b <= 1.0 for b in budgets) or len(set(budgets)) != len(budgets):
        raise ValueError(f"budgets must be distinct numbers in [0, 1], at least one; got {budgets}")
    lighter = {float(b) for b in light}
    if not lighter <= set(budgets):
        raise ValueError(f"light must name budgets of {budgets}; got {sorted(lighter)}")
    variants = PROXIMITY_VARIANTS if proximity == "both" else (proximity,)
    if conditions == "uncertainty-only":  # no c_prox: its reading changes nothing
        variants = variants[:1]
    configs = [("unperturbed", load_config(env))]
    configs += [(kind, perturbed_config(env, kind, strength)) for kind, strengths in CALIBRATION_SET.items()
                for strength in strengths]
    n_envs = min(episodes, 40)
    runs = [CalibrationRun(config, kind != "unperturbed", episodes, CALIBRATION_SEED + index * episodes, kind)
            for index, (kind, config) in enumerate(configs)]
    per_pass = episodes * len(runs)
    most_candidates = len(PROXY_BUDGET_SHARES) * len(variants) * len(CALIBRATION_LEADS) * len(PROXY_HOLDS)
    # collection, plain replay, candidates, refinement rounds
    played = {"done": 0,
              "total": per_pass * (2 + len(budgets) * (most_candidates + REFINE_ROUNDS * REFINE_PASSES))}

    def advance(n: int) -> None:
        played["done"] += n
        if progress is not None:
            progress(played["done"], played["total"])

    parts = [collect_records(policy, estimator, run.config, episodes, seed=run.seed, perturbed=run.perturbed,
                             window=window, n_envs=n_envs, episode_offset=index * episodes, progress=advance,
                             sensing=sensing).assign(group=run.group)
             for index, run in enumerate(runs)]
    records = pd.concat(parts, ignore_index=True)
    extra = {} if conditions == "paper" else {"conditions": conditions}  # paper reports as before the choice

    def common(budget: float) -> dict[str, Any]:
        return {"calibration_set": CALIBRATION_SET, "calibration_seed": CALIBRATION_SEED,
                "false_activation_budget": budget, "episodes_per_configuration": episodes,
                "proximity_searched": list(variants), "leads_searched": list(CALIBRATION_LEADS),
                "proxy_budgets": [share * budget for share in
                                  (PROXY_BUDGET_SHARES[:1] if budget in lighter else PROXY_BUDGET_SHARES)],
                "confidence": confidence,
                "sensing": sensing, **extra}

    if not records.loc[records["perturbed"], "collided"].any():
        # Nothing to learn from: the layer could only cost false activations, so it is switched off.
        thresholds = Thresholds.create(Thresholds.never().model_dump(), sensing=sensing)
        if progress is not None:  # nothing else to play: the bar ends full
            progress(played["done"], played["done"])
        return {budget: (thresholds, {"thresholds": thresholds.model_dump(), "prevented_fraction": float("nan"),
                                      "prevented_worst": float("nan"), "false_activation_rate": 0.0,
                                      "false_activation_upper": 0.0, "n_collisions": 0,
                                      "note": "no collision in the calibration episodes: thresholds that never fire",
                                      **common(budget)})
                for budget in budgets}
    full = [budget for budget in budgets if budget not in lighter]
    proposals = {budget: _proposals(records, budget, variants, conditions, sensing) for budget in full}
    distinct = {candidate for candidates, _ in proposals.values() for candidate in candidates}
    most_light = len(lighter) * len(variants) * len(CALIBRATION_LEADS) * len(PROXY_HOLDS)  # before they are known
    played["total"] = played["done"] + per_pass * (1 + len(distinct) + most_light
                                                   + len(full) * REFINE_ROUNDS * REFINE_PASSES)
    plain_collisions = rollout_scores(None, policy, estimator, runs, window, n_envs, advance)["collisions"]
    cache: dict[Thresholds, dict[str, Any]] = {}
    results: dict[float, tuple[Thresholds, dict[str, Any]]] = {}
    never = Thresholds.create(Thresholds.never().model_dump(), sensing=sensing)
    for budget in full + sorted(lighter):  # a light budget reads the c_prox readings the full ones chose
        if budget in lighter:
            readings = [v for v in variants if any(t.proximity == v and t != never for t, _ in results.values())]
            proposals[budget] = _proposals(records, budget, readings or variants, conditions, sensing,
                                           shares=PROXY_BUDGET_SHARES[:1])
        candidates, proxies = proposals[budget]
        thresholds, table = select_by_rollouts(candidates, policy, estimator, runs, budget, window, n_envs,
                                               confidence, progress=advance, plain_collisions=plain_collisions,
                                               cache=cache)
        table = pd.concat([table, pd.DataFrame(proxies)], axis=1).assign(stage="proxy")
        if budget not in lighter:
            thresholds, table = _refine(thresholds, table, plain_collisions, policy, estimator, runs, budget, window,
                                        n_envs, confidence, advance, cache)
        thresholds = Thresholds.create(thresholds.model_dump(), sensing=sensing)  # also when none met the budget
        chosen = table[table["chosen"]]
        report = {"thresholds": thresholds.model_dump(), "n_collisions": int(table["plain_collisions"].iloc[0]),
                  "prevented_fraction": float(chosen["prevented_fraction"].iloc[0]) if len(chosen) else 0.0,
                  "prevented_worst": float(chosen["prevented_worst"].iloc[0]) if len(chosen) else 0.0,
                  "false_activation_rate": float(chosen["false_activation_rate"].iloc[0]) if len(chosen) else 0.0,
                  "false_activation_upper": float(chosen["false_activation_upper"].iloc[0]) if len(chosen) else 0.0,
                  "candidates": table.to_dict(orient="records"), **common(budget)}
        if not len(chosen):
            report["note"] = ("no candidate met the false-activation budget in the calibration rollouts (at the "
                              f"{confidence:.0%} upper bound): thresholds that never fire")
        if budget in lighter:
            report["search"] = "light"
        results[budget] = (thresholds, report)
    played["total"] = played["done"]  # the refinement may stop early: the bar ends full
    if progress is not None:
        progress(played["done"], played["total"])
    return {budget: results[budget] for budget in budgets}


def _proposals(records: pd.DataFrame, budget: float, variants: Sequence[str], conditions: str, sensing: str,
               shares: Sequence[float] = PROXY_BUDGET_SHARES) -> tuple[list[Thresholds], list[dict[str, Any]]]:
    """Stage 1 of `calibrate_thresholds` for one budget: the distinct proxy candidates (per budget share, proximity
    reading and lead), each with every hold of `PROXY_HOLDS`, and their proxy scores (one row per candidate)."""
    candidates: list[Thresholds] = []
    proxies: list[dict[str, Any]] = []
    for share in shares:
        for variant in variants:
            for lead in CALIBRATION_LEADS:
                try:
                    result = calibrate(records, false_activation_budget=share * budget, proximity=variant,
                                       lead=lead, conditions=conditions)
                except ValueError:
                    if conditions == "paper":  # always has a feasible rule (inf thresholds): a real error
                        raise
                    continue  # a rule without uncertainty condition may have none within this budget
                candidate = Thresholds.create(result.thresholds.model_dump(), sensing=sensing)
                if candidate not in candidates:
                    candidates.append(candidate)
                    proxies.append({"lead": lead, "proxy_budget": share * budget,
                                    "proxy_prevented_fraction": result.prevented_fraction,
                                    "proxy_worst_type_fraction": result.worst_type_fraction,
                                    "proxy_false_activation_rate": result.false_activation_rate})
    if not candidates:  # nothing within the budget: the rule that never fires is replayed (and not chosen)
        candidates, proxies = [Thresholds.create(Thresholds.never().model_dump(), sensing=sensing)], [{}]
    # The proxy cannot score a hold (module docstring): every proposed rule is replayed with each of PROXY_HOLDS, so
    # a hold can pair with a less eager rule than the one the per-step replays prefer (hold 0 first: it wins ties).
    return ([c.model_copy(update={"hold_steps": hold}) for hold in PROXY_HOLDS for c in candidates],
            [row for _ in PROXY_HOLDS for row in proxies])


def save_calibration(thresholds: Thresholds, report: dict[str, Any], path: str | Path) -> Path:
    """Write what `calibrate_thresholds` returned: the thresholds to `path` (``save_thresholds``: JSON for
    ``.json``, YAML otherwise) and the report, every candidate included, next to them as ``<path
    stem>.report.json``; returns the report's path."""
    path = Path(path)
    save_thresholds(thresholds, path)
    report_path = path.with_suffix(".report.json")
    # Infinity kept (an uncertainty threshold switched off), unlike the run units' strict JSON; default=str: values
    # JSON has no type for (e.g. in the candidates table) are written as their text.
    write_text_atomic(report_path, json.dumps(report, indent=2, default=str))
    return report_path
