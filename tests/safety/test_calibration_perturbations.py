"""The calibration and the perturbation registry: every registered perturbation type counts as perturbed in the
calibration records, and the types held out of the calibration (the behaviour shift) are never played there."""

from __future__ import annotations

import pandas as pd
import pytest

from socnav.config import load_config
from socnav.controllers import StraightController
from socnav.envs.perturbations import CALIBRATION_SET, PERTURBATIONS, perturbed_config, strength_zero
from socnav.safety import collect_records

WORLD = {"scenario": "position_swap", "n_humans": 1}


@pytest.mark.parametrize("name", list(PERTURBATIONS))
def test_collect_records_flags_every_registered_perturbation_as_perturbed(name):
    """Fails for a newly registered perturbation type the calibration would take for the unperturbed world (its
    episodes would then count as false activations instead of collisions to prevent)."""
    strongest = perturbed_config(WORLD, name, PERTURBATIONS[name].grid[-1])
    records = collect_records(StraightController(strongest), None, strongest, n_episodes=1, n_envs=1)
    assert len(records) and records["perturbed"].all()
    calm = perturbed_config(WORLD, name, strength_zero(name))
    records = collect_records(StraightController(calm), None, calm, n_episodes=1, n_envs=1)
    assert len(records) and not records["perturbed"].any()


def test_the_calibration_never_plays_the_behaviour_shift(monkeypatch):
    from socnav.safety.calibration import calibrate_budgets, workflow

    played = []

    def fake_collect(policy, estimator, config, n, seed=0, perturbed=None, episode_offset=0, progress=None, **kw):
        played.append((config, perturbed))
        progress(n)
        return pd.DataFrame({"episode": [episode_offset], "perturbed": [bool(perturbed)], "collided": [False]})

    monkeypatch.setattr(workflow, "collect_records", fake_collect)
    budgets = calibrate_budgets(None, None, WORLD, 2, [0.05])
    _, report = budgets[0.05]
    assert "no collision" in report["note"] and "behaviour_shift" not in report["calibration_set"]
    assert len(played) == 1 + sum(len(strengths) for strengths in CALIBRATION_SET.values())
    assert all(config.perturbation.human_model is None and config.humans.model == load_config(WORLD).humans.model
               for config, _ in played)
    # every registered type with calibration strengths is played, flagged perturbed; the held-out ones never
    assert [perturbed for _, perturbed in played] == [False] + [True] * (len(played) - 1)
    held_out = [name for name, p in PERTURBATIONS.items() if not p.calibration]
    assert "behaviour_shift" in held_out and not set(held_out) & set(CALIBRATION_SET)
    assert set(CALIBRATION_SET) == set(PERTURBATIONS) - set(held_out)
