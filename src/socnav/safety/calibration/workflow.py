"""The calibration workflow: records of the plain policy, then the three stages (proxy search, selection by
rollouts, refinement) for one false-activation budget or several, and the saving of what they chose.

:func:`calibrate_thresholds` is the whole calibration for one budget (what ``socnav calibrate`` runs);
:func:`calibrate_budgets` runs it for several budgets at once (a trade-off curve): the records and every replay are
played once and shared, a candidate proposed for two budgets is scored once. :func:`save_calibration` writes the
thresholds and the report.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from socnav.config import load_config
from socnav.envs.perturbations import CALIBRATION_SEED, CALIBRATION_SET, perturbed_config
from socnav.io import write_text_atomic
from socnav.safety.calibration.proxy_search import (
    CALIBRATION_LEADS,
    PROXY_BUDGET_SHARES,
    PROXY_HOLDS,
    propose_candidates,
)
from socnav.safety.calibration.records import collect_records
from socnav.safety.calibration.refinement import REFINE_PASSES, REFINE_ROUNDS, refine_by_rollouts
from socnav.safety.calibration.rollout_selection import CalibrationRun, rollout_scores, select_by_rollouts
from socnav.safety.rule import PROXIMITY_VARIANTS, Thresholds, check_conditions, save_thresholds

__all__ = ["calibrate_budgets", "calibrate_thresholds", "calibration_runs", "save_calibration"]


def calibrate_thresholds(policy: Any, estimator: Any, env: dict[str, Any], episodes: int, budget: float = 0.05,
                         proximity: str = "both", window: int = 4, confidence: float = 0.95,
                         progress: Callable[[int, int], None] | None = None,
                         sensing: str = "perceived", conditions: str = "paper") -> tuple[Thresholds, dict[str, Any]]:
    """Thresholds chosen on calibration episodes: `episodes` unperturbed ones and `episodes` per strength of
    `CALIBRATION_SET`, from episode seeds `CALIBRATION_SEED`... (disjoint from the evaluation's). A perturbation
    type registered without calibration strengths (the behaviour shift) is held out: never played here.

    Three stages. (1) The proxy search (`socnav.safety.calibration.select_by_proxy`) on per-step records of the
    plain policy proposes one candidate per proximity variant (`proximity`: one of `PROXIMITY_VARIANTS`, or
    `both`), lead in `CALIBRATION_LEADS` and proxy budget (`PROXY_BUDGET_SHARES` of `budget`): the proxy alone
    rewards a rule that fires at the very step of the contact, too late for the fallback when humans close fast, so
    candidates that must fire 1 or 2 steps earlier compete too. (2) `socnav.safety.select_by_rollouts` replays the
    same calibration episodes with each candidate's `SafePolicy`, each candidate once per fallback hold in
    `PROXY_HOLDS` (the proxy cannot score a hold), and keeps the one that prevents the most collisions (the worst
    perturbation type, then the mean over types) among those whose false-activation rate is within `budget` at
    `confidence` (one-sided upper bound), both MEASURED in those rollouts. (3) `refine_by_rollouts`: up to
    `REFINE_ROUNDS` rounds of measured hill-climbing towards eager neighbours of the chosen rule
    (`eager_neighbours`, a longer hold of the fallback among them), spending the margin between the proxy's and
    the measured false activation. Every stage scores per perturbation type, worst type first
    (`socnav.safety.calibration.proxy_search`): no type is traded for another. The report's ``candidates`` lists
    every rule tried with its ``stage`` (``proxy``, ``refine-1``, ...).

    `progress(done, total)`: episodes played so far and in all (the total shrinks once the number of distinct
    candidates is known; it starts at the most there can be).

    `sensing` (``perceived`` | ``true``, `socnav.safety.Thresholds.sensing`): what the rule's proximity terms and
    the fallback read, in the records and the replays alike; the thresholds returned carry it.

    `conditions` (`socnav.safety.Thresholds.conditions`): the rule variant calibrated -- eq. (10) (``paper``) or one
    of its ablations, each searching only the parameters it reads (`select_by_proxy`, `eager_neighbours`); an
    ``uncertainty-only`` rule has no c_prox, so one proximity reading is enough. A ``proximity-only`` rule reads no
    uncertainty: `estimator` may then be None (nothing is estimated; much cheaper).

    Several budgets on the same episodes: `calibrate_budgets`.

    :return: ``(thresholds, report)``; without any collision to learn from, thresholds that never fire.
    """
    return calibrate_budgets(policy, estimator, env, episodes, [budget], proximity, window, confidence, progress,
                             sensing, conditions)[budget]


class _EpisodeTally:
    """Episodes played so far and in all, reported to ``progress(done, total)`` at every advance."""

    def __init__(self, progress: Callable[[int, int], None] | None, total: int) -> None:
        self.progress, self.done, self.total = progress, 0, total

    def advance(self, n: int) -> None:
        """``n`` more episodes played."""
        self.done += n
        if self.progress is not None:
            self.progress(self.done, self.total)

    def finish(self) -> None:
        """Nothing more to play (the refinement may stop early): the bar ends full."""
        self.total = self.done
        if self.progress is not None:
            self.progress(self.done, self.total)


@dataclass
class _Replays:
    """What every replay of one calibration shares: the policy, its estimator, the calibration runs and how they
    are played, the plain policy's collisions per type (measured once) and the replays already played."""

    policy: Any
    estimator: Any
    runs: list[CalibrationRun]
    window: int
    n_envs: int
    confidence: float
    progress: Callable[[int], None]
    plain_collisions: dict[str, int] = field(default_factory=dict)
    cache: dict[Thresholds, dict[str, Any]] = field(default_factory=dict)


def _checked_budgets(budgets: Sequence[float], light: Sequence[float], proximity: str,
                     conditions: str) -> tuple[list[float], set[float], tuple[str, ...]]:
    """``(budgets, light budgets, proximity readings searched)`` of `calibrate_budgets`' arguments, after checking
    them (``ValueError`` naming the bad one and what is allowed)."""
    if proximity != "both" and proximity not in PROXIMITY_VARIANTS:
        raise ValueError(f"proximity must be one of: both, {', '.join(PROXIMITY_VARIANTS)}; got {proximity!r}")
    check_conditions(conditions)
    checked = [float(b) for b in budgets]
    if not checked or any(not 0.0 <= b <= 1.0 for b in checked) or len(set(checked)) != len(checked):
        raise ValueError(f"budgets must be distinct numbers in [0, 1], at least one; got {checked}")
    lighter = {float(b) for b in light}
    if not lighter <= set(checked):
        raise ValueError(f"light must name budgets of {checked}; got {sorted(lighter)}")
    variants = PROXIMITY_VARIANTS if proximity == "both" else (proximity,)
    if conditions == "uncertainty-only":  # no c_prox: its reading changes nothing
        variants = variants[:1]
    return checked, lighter, variants


def calibration_runs(env: dict[str, Any], episodes: int) -> list[CalibrationRun]:
    """The unperturbed configuration and one per strength of `CALIBRATION_SET`, ``episodes`` each, on consecutive
    blocks of episode seeds from `CALIBRATION_SEED`."""
    configs = [("unperturbed", load_config(env))]
    configs += [(kind, perturbed_config(env, kind, strength)) for kind, strengths in CALIBRATION_SET.items()
                for strength in strengths]
    return [CalibrationRun(config, kind != "unperturbed", episodes, CALIBRATION_SEED + index * episodes, kind)
            for index, (kind, config) in enumerate(configs)]


def _collect(policy: Any, estimator: Any, runs: Sequence[CalibrationRun], episodes: int, window: int, n_envs: int,
             sensing: str, progress: Callable[[int], None]) -> pd.DataFrame:
    """The calibration records of every run (episode ids offset per run; ``group``: the run's perturbation type)."""
    parts = [collect_records(policy, estimator, run.config, episodes, seed=run.seed, perturbed=run.perturbed,
                             window=window, n_envs=n_envs, episode_offset=index * episodes, progress=progress,
                             sensing=sensing).assign(group=run.group)
             for index, run in enumerate(runs)]
    return pd.concat(parts, ignore_index=True)


def _report_common(budget: float, light: bool, episodes: int, variants: Sequence[str], confidence: float,
                   sensing: str, conditions: str) -> dict[str, Any]:
    """The report's description of the calibration of one budget (what was searched, on which episodes)."""
    # a paper rule's report leaves `conditions` out, as its thresholds' dump does
    extra = {} if conditions == "paper" else {"conditions": conditions}
    return {"calibration_set": CALIBRATION_SET, "calibration_seed": CALIBRATION_SEED,
            "false_activation_budget": budget, "episodes_per_configuration": episodes,
            "proximity_searched": list(variants), "leads_searched": list(CALIBRATION_LEADS),
            "proxy_budgets": [share * budget for share in
                              (PROXY_BUDGET_SHARES[:1] if light else PROXY_BUDGET_SHARES)],
            "confidence": confidence,
            "sensing": sensing, **extra}


def _never_firing(budgets: Sequence[float], sensing: str,
                  common: Callable[[float], dict[str, Any]]) -> dict[float, tuple[Thresholds, dict[str, Any]]]:
    """Every budget's result when the calibration episodes hold no collision: nothing to learn from, the layer
    could only cost false activations, so it is switched off."""
    thresholds = Thresholds.create(Thresholds.never().model_dump(), sensing=sensing)
    return {budget: (thresholds, {"thresholds": thresholds.model_dump(), "prevented_fraction": float("nan"),
                                  "prevented_worst": float("nan"), "false_activation_rate": 0.0,
                                  "false_activation_upper": 0.0, "n_collisions": 0,
                                  "note": "no collision in the calibration episodes: thresholds that never fire",
                                  **common(budget)})
            for budget in budgets}


def _choose(budget: float, candidates: list[Thresholds], proxies: list[dict[str, Any]], replays: _Replays,
            refine: bool) -> tuple[Thresholds, pd.DataFrame]:
    """Stages 2 and (if ``refine``) 3 for one budget, from stage 1's ``candidates`` and their proxy scores:
    the rule chosen and the table of every rule tried (with its ``stage``)."""
    r = replays
    thresholds, table = select_by_rollouts(candidates, r.policy, r.estimator, r.runs, budget, r.window, r.n_envs,
                                           r.confidence, progress=r.progress, plain_collisions=r.plain_collisions,
                                           cache=r.cache)
    assert isinstance(thresholds, Thresholds)  # the rule's candidates give the rule's choice
    table = pd.concat([table, pd.DataFrame(proxies)], axis=1).assign(stage="proxy")
    if refine:
        thresholds, table = refine_by_rollouts(thresholds, table, r.plain_collisions, r.policy, r.estimator, r.runs,
                                               budget, r.window, r.n_envs, r.confidence, r.progress, r.cache)
    return thresholds, table


def _budget_report(thresholds: Thresholds, table: pd.DataFrame, confidence: float,
                   common: dict[str, Any]) -> dict[str, Any]:
    """The report of one budget: the thresholds chosen, the measured scores of the chosen row of ``table`` (0
    without one) and every candidate tried."""
    chosen = table[table["chosen"]]
    report = {"thresholds": thresholds.model_dump(), "n_collisions": int(table["plain_collisions"].iloc[0]),
              "prevented_fraction": float(chosen["prevented_fraction"].iloc[0]) if len(chosen) else 0.0,
              "prevented_worst": float(chosen["prevented_worst"].iloc[0]) if len(chosen) else 0.0,
              "false_activation_rate": float(chosen["false_activation_rate"].iloc[0]) if len(chosen) else 0.0,
              "false_activation_upper": float(chosen["false_activation_upper"].iloc[0]) if len(chosen) else 0.0,
              "candidates": table.to_dict(orient="records"), **common}
    if not len(chosen):
        report["note"] = ("no candidate met the false-activation budget in the calibration rollouts (at the "
                          f"{confidence:.0%} upper bound): thresholds that never fire")
    return report


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
    budgets, lighter, variants = _checked_budgets(budgets, light, proximity, conditions)
    runs = calibration_runs(env, episodes)
    n_envs = min(episodes, 40)
    per_pass = episodes * len(runs)
    most_candidates = len(PROXY_BUDGET_SHARES) * len(variants) * len(CALIBRATION_LEADS) * len(PROXY_HOLDS)
    # collection, plain replay, candidates, refinement rounds
    played = _EpisodeTally(progress, per_pass * (2 + len(budgets) * (most_candidates + REFINE_ROUNDS * REFINE_PASSES)))
    records = _collect(policy, estimator, runs, episodes, window, n_envs, sensing, played.advance)

    def common(budget: float) -> dict[str, Any]:
        return _report_common(budget, budget in lighter, episodes, variants, confidence, sensing, conditions)

    if not records.loc[records["perturbed"], "collided"].any():
        played.finish()  # nothing else to play
        return _never_firing(budgets, sensing, common)
    full = [budget for budget in budgets if budget not in lighter]
    proposals = {budget: propose_candidates(records, budget, variants, conditions, sensing) for budget in full}
    distinct = {candidate for candidates, _ in proposals.values() for candidate in candidates}
    most_light = len(lighter) * len(variants) * len(CALIBRATION_LEADS) * len(PROXY_HOLDS)  # before they are known
    played.total = played.done + per_pass * (1 + len(distinct) + most_light + len(full) * REFINE_ROUNDS * REFINE_PASSES)
    plain_collisions = rollout_scores(None, policy, estimator, runs, window, n_envs, played.advance)["collisions"]
    replays = _Replays(policy, estimator, runs, window, n_envs, confidence, played.advance, plain_collisions)
    results: dict[float, tuple[Thresholds, dict[str, Any]]] = {}
    never = Thresholds.create(Thresholds.never().model_dump(), sensing=sensing)
    for budget in full + sorted(lighter):  # a light budget reads the c_prox readings the full ones chose
        if budget in lighter:
            readings = [v for v in variants if any(t.proximity == v and t != never for t, _ in results.values())]
            proposals[budget] = propose_candidates(records, budget, readings or variants, conditions, sensing,
                                                   shares=PROXY_BUDGET_SHARES[:1])
        candidates, proxies = proposals[budget]
        thresholds, table = _choose(budget, candidates, proxies, replays, refine=budget not in lighter)
        thresholds = Thresholds.create(thresholds.model_dump(), sensing=sensing)  # also when none met the budget
        report = _budget_report(thresholds, table, confidence, common(budget))
        if budget in lighter:
            report["search"] = "light"
        results[budget] = (thresholds, report)
    played.finish()
    return {budget: results[budget] for budget in budgets}


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
