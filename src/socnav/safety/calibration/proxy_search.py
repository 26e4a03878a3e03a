"""Stage 1 of the calibration: the proxy search, an exhaustive grid search over the rule's thresholds scored on
calibration records, and the candidates it proposes to the rollout selection (stage 2).

**Objective -- a documented proxy.** Whether the fallback would have prevented a collision cannot be known
without re-running the episode with it. We count a collision of a perturbed episode as *preventable* if the rule
would have fired at one of the last ``lookback`` steps up to and including ``collision_step`` (default 4 steps =
1 s at dt = 0.25 s), or, with ``lead > 0``, up to ``collision_step - lead`` only (firing at the contact step
itself is too late when a human closes fast). :func:`select_by_proxy` chooses ``(lambda_ep, lambda_feat,
lambda_prox, beta1)`` maximising the fraction of perturbed-episode collisions flagged so, subject to the
fallback-activation rate -- the fraction of steps of UNPERTURBED episodes where the rule fires -- being at most
``false_activation_budget``. Ties go to the lowest activation rate, then to the least eager rule (larger
``lambda_ep``, larger ``lambda_feat``, smaller ``lambda_prox``, smaller ``beta1``). ``inf`` for an uncertainty
threshold means that condition is switched off.

**Per perturbation type, worst type first.** With a ``group`` column (the perturbation type of each perturbed
episode), the flagged fraction is computed per type and rules are ranked by the WORST type's fraction, then by the
mean over types (then as above). Pooled counts let the type with the most collisions decide (e.g. more humans,
hundreds of collisions, over faster humans, a dozen), and even an equal-weight mean trades one type for another: in
Table 3 two rules with the same mean (71 %) prevented 98.6 % / 22 % and 13 % / 94 % of the observation-noise /
faster-humans collisions. A safety layer is judged by the perturbation it handles worst, so the calibration
maximises that (max-min) and uses the mean only to break ties.

**The grid.** Quantile-based candidates (midpoints between distinct quantiles of the records, over all rows and
over the collision-window rows, so resolution is where it matters) for the three lambdas and a fixed ``beta1``
list, or explicit candidate lists given in ``grid``. All ``lambda_ep`` x ``lambda_feat`` pairs of one ``(beta1,
lambda_prox)`` are scored at once with 2-D cumulative histograms, so large grids are cheap. The search is
deterministic.

**Rule variants.** The rule's ablations (``Thresholds.conditions``: ``proximity-only``, ``uncertainty-only``) are
searched over only the parameters they read (:data:`SEARCHED_KEYS`; the others get :data:`NEUTRAL_VALUES`), so
every variant is chosen under the same false-activation budget on the same records.

The proxy scores the per-step rule (``hold_steps = 0``): a hold of the fallback (``Thresholds.hold_steps``) changes
the trajectories it is meant to change, so only replays can score it; :func:`propose_candidates` therefore hands
every proposed rule to stage 2 once per hold of :data:`PROXY_HOLDS`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np
import pandas as pd

from socnav.safety.calibration.records import validate_records
from socnav.safety.rule import (
    Conditions,
    Proximity,
    Thresholds,
    check_conditions,
    check_proximity,
    proximity_score,
    rule_conditions,
)

__all__ = [
    "CALIBRATION_LEADS",
    "DEFAULT_BETA1_GRID",
    "GRID_KEYS",
    "NEUTRAL_VALUES",
    "PROXY_BUDGET_SHARES",
    "PROXY_HOLDS",
    "SEARCHED_KEYS",
    "ProxySearchResult",
    "propose_candidates",
    "proxy_scores",
    "select_by_proxy",
]

DEFAULT_BETA1_GRID = (0.0, 0.25, 0.5, 1.0, 2.0)
GRID_KEYS = ("lambda_ep", "lambda_feat", "lambda_prox", "beta1")
#: The parameters each rule variant (`Thresholds.conditions`) reads, i.e. the ones its calibration searches.
SEARCHED_KEYS: dict[str, tuple[str, ...]] = {"paper": GRID_KEYS, "proximity-only": ("lambda_prox", "beta1"),
                                              "uncertainty-only": ("lambda_ep", "lambda_feat")}
#: What the calibration writes for the parameters of a removed condition (ignored by that rule): the values under
#: which the removed condition (nearly) always holds in eq. (10) -- any uncertainty above 0, any human within 1 km.
NEUTRAL_VALUES: dict[str, float] = {"lambda_ep": 0.0, "lambda_feat": 0.0, "lambda_prox": 1000.0, "beta1": 0.0}
#: Leads searched by the calibration proxy: the rule must fire at least this many steps before the collision step.
CALIBRATION_LEADS = (0, 1, 2)
#: The proxy search also runs at these fractions of the budget: candidates with a margin below it.
PROXY_BUDGET_SHARES = (1.0, 0.5)
#: Fallback holds (`Thresholds.hold_steps`) each proposed rule is replayed with in stage 2.
PROXY_HOLDS = (0, 1)


@dataclass(frozen=True)
class ProxySearchResult:
    """The thresholds :func:`select_by_proxy` chose and their proxy scores on the calibration records.

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
    check_proximity(proximity)
    column = "relative_speed" if proximity == "abs-relative-speed" else "closing_speed"
    if column not in records:
        raise ValueError(f"records need a {column!r} column for proximity={proximity!r}")
    return records[column].to_numpy(np.float64)


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
    quantiles = []
    for data in (values, focus):
        data = data[np.isfinite(data)]
        if data.size:
            quantiles.append(np.quantile(data, levels))
    points = np.unique(np.concatenate(quantiles)) if quantiles else np.zeros(0)
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
    episode_type = dict(zip(episode_codes[collided_rows], labels[collided_rows], strict=True))
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

def proxy_scores(records: pd.DataFrame, thresholds: Thresholds, lookback: int = 4,
                 lead: int = 0) -> dict[str, float]:
    """The calibration proxy of given thresholds on records (via the rule itself): ``prevented_fraction`` (the mean
    of the per-type fractions with a ``group`` column), ``worst_type_fraction``, ``false_activation_rate``,
    ``n_collisions``, ``n_unperturbed_steps``. It scores the per-step rule: ``thresholds.hold_steps`` is ignored
    (a hold changes the trajectories the records come from; `rollout_scores` measures it)."""
    _check_lead(lookback, lead)
    records = validate_records(records)
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


# ------------------------------------------------------------------------------------------------ the search

def _searched_keys(false_activation_budget: float, grid: Mapping[str, Sequence[float]] | None, lookback: int,
                   lead: int, conditions: str) -> tuple[str, ...]:
    """The parameters :func:`select_by_proxy` searches, after checking its arguments (``ValueError`` naming the
    bad one and what is allowed)."""
    if not 0.0 <= false_activation_budget <= 1.0:
        raise ValueError(f"false_activation_budget must be in [0, 1], got {false_activation_budget}")
    _check_lead(lookback, lead)
    check_conditions(conditions)
    searched = SEARCHED_KEYS[conditions]
    if grid is not None:
        unknown = set(grid) - set(GRID_KEYS)
        if unknown:
            raise ValueError(f"unknown grid keys {sorted(unknown)}; allowed: {', '.join(GRID_KEYS)}")
        ignored = sorted(set(grid) - set(searched))
        if ignored:
            raise ValueError(f"grid keys {ignored} are not searched for conditions={conditions!r} (the rule ignores "
                             f"them); allowed: {', '.join(searched)}")
    return searched


def _uncertainty_grid(records: pd.DataFrame, window: np.ndarray, searched: Sequence[str],
                      grid: Mapping[str, Sequence[float]] | None,
                      n_quantiles: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(lambda_ep, lambda_feat, k_ep, k_feat)``: the uncertainty thresholds searched and each row's bins in them
    (:func:`_bins`)."""
    if "lambda_ep" not in searched:  # proximity-only: one "uncertainty condition", holding on every row (k = 1 > a = 0)
        return (np.array([NEUTRAL_VALUES["lambda_ep"]]), np.array([NEUTRAL_VALUES["lambda_feat"]]),
                np.ones(len(records), dtype=np.int64), np.zeros(len(records), dtype=np.int64))
    u_ep = records["u_ep_heading"].to_numpy(np.float64)
    u_feat = records["u_feat"].to_numpy(np.float64)
    lambda_ep = _explicit(grid, "lambda_ep")
    lambda_ep = _candidates(u_ep, u_ep[window], n_quantiles, True) if lambda_ep is None else lambda_ep
    lambda_feat = _explicit(grid, "lambda_feat")
    lambda_feat = _candidates(u_feat, u_feat[window], n_quantiles, True) if lambda_feat is None else lambda_feat
    return lambda_ep, lambda_feat, _bins(u_ep, lambda_ep), _bins(u_feat, lambda_feat)


def _proximity_gates(score: np.ndarray, gap: np.ndarray, approaching: np.ndarray, window: np.ndarray,
                     fixed_prox: np.ndarray | None, n_quantiles: int,
                     conditions: str) -> list[tuple[float, np.ndarray]]:
    """``(lambda_prox, gate)`` per proximity threshold searched for one ``beta1`` (its proximity ``score``): the
    gate is where ``c_prox`` and ``c_ap`` hold."""
    prox_candidates = _prox_candidates(score, approaching, window, n_quantiles) if fixed_prox is None else fixed_prox
    if fixed_prox is None and conditions == "proximity-only":  # a gate that (almost) never opens: with no
        prox_candidates = np.unique(np.append(prox_candidates, 0.0))  # uncertainty grid, no inf to fall on
    return [(lam_prox, approaching & np.isfinite(gap) & (score < lam_prox)) for lam_prox in prox_candidates]


def _frontier_rows(records: pd.DataFrame, perturbed: np.ndarray, window: np.ndarray, searched: Sequence[str],
                   grid: Mapping[str, Sequence[float]] | None, proximity: Proximity, n_quantiles: int,
                   conditions: str, false_activation_budget: float) -> list[dict[str, Any]]:
    """The frontier: per ``(beta1, lambda_prox)``, the best ``(lambda_ep, lambda_feat)`` within the budget and its
    scores (none for a gate with no pair within it)."""
    gap = records["gap"].to_numpy(np.float64)
    previous_gap = records["previous_gap"].to_numpy(np.float64)
    approaching = np.isnan(previous_gap) | (gap <= previous_gap)  # c_ap, as in the rule
    lambda_ep, lambda_feat, k_ep, k_feat = _uncertainty_grid(records, window, searched, grid, n_quantiles)
    scorer = _GridScorer(records, perturbed, window, k_ep, k_feat, len(lambda_ep), len(lambda_feat))
    if "lambda_prox" in searched:
        speed = _speed_column(records, proximity)
        betas = _explicit(grid, "beta1")
        betas = np.asarray(DEFAULT_BETA1_GRID) if betas is None else betas
    else:  # uncertainty-only: no c_prox, one gate (c_ap)
        speed, betas = np.zeros(len(records)), np.array([NEUTRAL_VALUES["beta1"]])
    fixed_prox = _explicit(grid, "lambda_prox")
    rows: list[dict[str, Any]] = []
    for beta in betas:
        if "lambda_prox" in searched:
            score = proximity_score(gap, speed, float(beta), proximity)
            gates = _proximity_gates(score, gap, approaching, window, fixed_prox, n_quantiles, conditions)
        else:
            gates = [(NEUTRAL_VALUES["lambda_prox"], approaching)]
        for lam_prox, gate in gates:
            false_rate, worst, prevented = scorer.score(gate)
            best = _best_feasible(false_rate, worst, prevented, false_activation_budget)
            if best is None:
                continue
            a, b = best
            rows.append({"beta1": float(beta), "lambda_prox": float(lam_prox),
                         "lambda_ep": float(lambda_ep[a]), "lambda_feat": float(lambda_feat[b]),
                         "prevented_fraction": float(prevented[a, b]),
                         "worst_type_fraction": float(worst[a, b]),
                         "false_activation_rate": float(false_rate[a, b])})
    return rows


def select_by_proxy(
    records: pd.DataFrame,
    false_activation_budget: float = 0.05,
    grid: Mapping[str, Sequence[float]] | None = None,
    lookback: int = 4,
    proximity: Proximity = "abs-relative-speed",
    n_quantiles: int = 41,
    lead: int = 0,
    conditions: Conditions = "paper",
) -> ProxySearchResult:
    """Stage 1: choose the rule's thresholds on calibration records by the proxy (module docstring; the records'
    format: `socnav.safety.calibration.records`).

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
    searched = _searched_keys(false_activation_budget, grid, lookback, lead, conditions)
    records = validate_records(records)
    perturbed = records["perturbed"].to_numpy(bool)
    n_unperturbed = int((~perturbed).sum())
    if n_unperturbed == 0:
        raise ValueError("calibration records hold no unperturbed steps: the false-activation rate is undefined")
    window = _window_rows(records, lookback, lead)
    n_collisions = len(records.loc[perturbed & records["collided"].to_numpy(bool), "episode"].unique())
    if n_collisions == 0:
        raise ValueError("no collisions in the perturbed episodes of the records: nothing to calibrate for")
    frontier_rows = _frontier_rows(records, perturbed, window, searched, grid, proximity, n_quantiles, conditions,
                                   false_activation_budget)
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
    return ProxySearchResult(
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


# ------------------------------------------------------------------------------------------------ proposing

def propose_candidates(records: pd.DataFrame, budget: float, variants: Sequence[str], conditions: str,
                       sensing: str, shares: Sequence[float] = PROXY_BUDGET_SHARES
                       ) -> tuple[list[Thresholds], list[dict[str, Any]]]:
    """Stage 1 of `socnav.safety.calibrate_thresholds` for one budget: the distinct :func:`select_by_proxy` choices
    per budget share (``shares`` of ``budget``), proximity reading (``variants``) and lead
    (:data:`CALIBRATION_LEADS`), each with every hold of :data:`PROXY_HOLDS` and with ``sensing``, and their proxy
    scores (one row per candidate; ``{}`` for the rule that never fires, proposed when nothing meets the budget)."""
    candidates: list[Thresholds] = []
    proxies: list[dict[str, Any]] = []
    for share in shares:
        for variant in variants:
            for lead in CALIBRATION_LEADS:
                try:
                    result = select_by_proxy(records, false_activation_budget=share * budget,
                                             proximity=cast(Proximity, variant), lead=lead,
                                             conditions=cast(Conditions, conditions))
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
