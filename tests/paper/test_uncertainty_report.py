"""Report sections of the `uncertainty` experiment kind: Table 2, Figs. 5-6, Table 3 and the safety layer's cost,
checked on hand-made Parquet records against values computed by hand (see the comments next to each number)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from socnav.experiments.registry import SECTIONS
from socnav.experiments.report import build_report
from socnav.io import write_table_atomic

# ------------------------------------------------------------------------------------------------ study records
# (strength, episode, u_feat per step, nearest_gap per step, w_u_feat per step, outcome); episode ids restart at
# every strength. Other raw uncertainties are derived below per estimator.
STUDY = {
    ("mc", "observation_noise"): [
        (0.0, 0, [1, 3], [1.0, 0.5], [0.1, 0.2], "goal"),         # episode mean 2; closest approach -> 0.2
        (0.0, 1, [4], [0.8], [0.3], "goal"),                      # mean 4 -> u(0) = 3 (per-step pooled: 2.67)
        (1.0, 0, [5], [0.4], [0.4], "goal"),
        (1.0, 1, [5], [0.6], [0.5], "collision"),                 # before collision -> 0.5
        (2.0, 0, [6, 6, 9], [0.9, 0.2, 0.7], [0.6, 0.7, 0.8], "goal"),  # mean 7; closest -> 0.7
        (2.0, 1, [11], [0.3], [0.9], "collision"),                # mean 11 -> u(2) = 9; before collision 0.9
    ],
    ("ensemble", "observation_noise"): [
        (0.0, 0, [1, 1], [1.0, 0.9], [0.01, 0.02], "goal"),       # u(0) = 1; closest -> 0.02
        (0.0, 1, [1], [0.5], [0.03], "collision"),
        (1.0, 0, [1.5], [0.5], [0.04], "goal"),
        (2.0, 0, [1, 3, 2], [0.5, 0.4, 0.6], [0.05, 0.06, 0.07], "goal"),  # mean 2; closest -> 0.06
        (2.0, 1, [2], [0.2], [0.08], "collision"),                # u(2) = 2
    ],
    ("mc", "more_humans"): [
        (2.0, 0, [2], [0.5], [1.0], "goal"),                      # u(2) = 2
        (7.0, 0, [4, 5], [0.3, 0.1], [1.1, 1.2], "collision"),    # u(7) = 4.5 -> (4.5 - 2) / (2 * 5) = 0.25
    ],
}


def _derived(estimator: str, strength: float, feat: np.ndarray) -> dict[str, np.ndarray]:
    if estimator == "mc":
        return {"u_ep_heading": feat / 10, "u_ep_speed": np.zeros_like(feat), "u_al_heading": np.full_like(feat, 0.5),
                "u_al_speed": 2 * feat}
    return {"u_ep_heading": feat / 10, "u_ep_speed": np.ones_like(feat),
            "u_al_heading": np.full_like(feat, 0.5 if strength == 0 else 1.0), "u_al_speed": 2 * feat}


def _steps(estimator: str, perturbation: str) -> pd.DataFrame:
    frames = []
    for strength, episode, feat, gaps, windowed, outcome in STUDY[(estimator, perturbation)]:
        feat = np.asarray(feat, dtype=float)
        n = len(feat)
        frame = pd.DataFrame({"estimator": estimator, "perturbation": perturbation, "strength": strength,
                              "episode": episode, "step": np.arange(n), "u_feat": feat,
                              **_derived(estimator, strength, feat), "nearest_gap": gaps,
                              "nearest_relative_speed": 0.5, "outcome": [""] * (n - 1) + [outcome]})
        for column in ("u_ep_heading", "u_ep_speed", "u_al_heading", "u_al_speed", "u_feat"):
            frame[f"w_{column}"] = frame[column]
        frame["w_u_feat"] = windowed
        frames.append(frame)
    # stored shuffled: the report must not rely on the row order
    return pd.concat(frames, ignore_index=True).sample(frac=1.0, random_state=3).reset_index(drop=True)


# ------------------------------------------------------------------------------------------------ safety records
G, C, T = "goal", "collision", "timeout"
# (estimator, perturbation, repeat, variant) -> {strength: outcomes}; every variant plays the same seeds.
SAFETY = {
    # observation noise, sigma(0) = 0: the unperturbed collisions of repeat 0 must not count.
    ("mc", "observation_noise", 0, "none"): {0.0: [C, G], 1.0: [C, C], 2.0: [C, G]},        # C_none = 3
    ("mc", "observation_noise", 0, "paper"): {0.0: [C, G], 1.0: [G, G], 2.0: [C, G]},       # 1 -> 66.67 %
    ("mc", "observation_noise", 0, "calibrated"): {0.0: [G, G], 1.0: [C, G], 2.0: [C, G]},  # 2 -> 33.33 %
    ("mc", "observation_noise", 1, "none"): {1.0: [C, G], 2.0: [G, G]},                     # C_none = 1
    ("mc", "observation_noise", 1, "paper"): {1.0: [G, G], 2.0: [G, G]},                    # 0 -> 100 %
    ("mc", "observation_noise", 1, "calibrated"): {1.0: [C, G], 2.0: [G, G]},               # 1 -> 0 %
    # faster humans, sigma(0) = 1: no perturbed collision without the layer -> undefined
    ("mc", "faster_humans", 0, "none"): {1.0: [C], 4.0: [G, G]},
    ("mc", "faster_humans", 0, "paper"): {1.0: [G], 4.0: [C, G]},
    ("mc", "faster_humans", 0, "calibrated"): {1.0: [G], 4.0: [C, G]},
    ("mc", "faster_humans", 1, "none"): {4.0: [G, G]},
    ("mc", "faster_humans", 1, "paper"): {4.0: [G, G]},
    ("mc", "faster_humans", 1, "calibrated"): {4.0: [G, G]},
    # heading / speed noise (paper thresholds only): pooled into "action noise"
    ("mc", "heading_noise", 0, "none"): {1.0: [C, C]},    # 2
    ("mc", "heading_noise", 0, "paper"): {1.0: [C, G]},   # 1 -> 50 %
    ("mc", "heading_noise", 1, "none"): {1.0: [C, G]},    # 1
    ("mc", "heading_noise", 1, "paper"): {1.0: [C, G]},   # 1 -> 0 %
    ("mc", "speed_noise", 0, "none"): {1.0: [C, G]},      # 1
    ("mc", "speed_noise", 0, "paper"): {1.0: [G, G]},     # 0 -> 100 %
    ("mc", "speed_noise", 1, "none"): {1.0: [G, G]},      # 0 -> undefined
    ("mc", "speed_noise", 1, "paper"): {1.0: [G, G]},
    # ensemble, observation noise only
    ("ensemble", "observation_noise", 0, "none"): {0.0: [G], 1.0: [C, G], 2.0: [C, C]},   # 3
    ("ensemble", "observation_noise", 0, "paper"): {0.0: [G], 1.0: [G, G], 2.0: [C, G]},  # 1 -> 66.67 %
    ("ensemble", "observation_noise", 1, "none"): {0.0: [G], 1.0: [G, G], 2.0: [C, G]},   # 1
    ("ensemble", "observation_noise", 1, "paper"): {0.0: [T], 1.0: [G, G], 2.0: [G, C]},  # 1 -> 0 %
}
LENGTH = {G: 10, C: 6, T: 20}
FALLBACK = {G: 1, C: 3, T: 5}


def _safety(estimator: str, perturbation: str) -> pd.DataFrame:
    rows = []
    for (est, pert, repeat, variant), strengths in SAFETY.items():
        if (est, pert) != (estimator, perturbation):
            continue
        for index, (strength, outcomes) in enumerate(strengths.items()):
            for k, outcome in enumerate(outcomes):
                rows.append({"estimator": est, "perturbation": pert, "strength": strength, "repeat": repeat,
                             "variant": variant, "episode": k, "seed": 1000 * repeat + 100 * index + k,
                             "outcome": outcome, "return": 1.0, "length": LENGTH[outcome],
                             "duration": 0.25 * LENGTH[outcome], "path_length": 3.0,
                             "time_to_goal": 2.5 + 0.5 * strength if outcome == G else np.nan,
                             "min_gap": 0.3, "intrusion_steps": 0, "intrusion_events": 0,
                             "fallback_steps": 0 if variant == "none" else FALLBACK[outcome]})
    return pd.DataFrame(rows)


def _run_dir(root: Path, study: bool = True, safety: bool = True, calibration: bool = True,
             units: list | None = None) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    (root / "resolved.json").write_text(json.dumps({"experiment": {"name": "unc", "kind": "uncertainty",
                                                                   "budget": "quick"}}))
    (root / "units.json").write_text(json.dumps(units or []))
    if study:
        for estimator, perturbation in STUDY:
            write_table_atomic(_steps(estimator, perturbation),
                               root / "study" / estimator / perturbation / "steps.parquet")
    if safety:
        for estimator, perturbation in {(e, p) for e, p, _, _ in SAFETY}:
            write_table_atomic(_safety(estimator, perturbation),
                               root / "safety" / estimator / perturbation / "episodes.parquet")
    if calibration:
        path = root / "calibrate" / "mc" / "calibration.json"
        path.parent.mkdir(parents=True)
        path.write_text(json.dumps({"thresholds": {"lambda_ep": 0.05, "lambda_feat": 0.25, "lambda_prox": 1.0,
                                                   "beta1": 0.25}, "prevented_fraction": 0.8,
                                    "false_activation_rate": 0.01}))
    return root


def _cells(markdown: str) -> list[list[str]]:
    return [[c.strip() for c in line.strip().strip("|").split("|")] for line in markdown.strip().splitlines()[2:]]


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> tuple[Path, str]:
    root = _run_dir(tmp_path_factory.mktemp("unc") / "run")
    page = build_report(root)
    return page.parent, page.read_text()


def test_sections_are_registered_for_the_uncertainty_kind():
    names = [name for name, _ in SECTIONS["uncertainty"]]
    # the page order of socnav.paper.uncertainty.report.PAGE: what the uncertainty knows comes last
    assert names[:6] == ["table2", "table2_claims", "uncertainty_vs_strength", "feature_uncertainty_collisions",
                         "table3", "table3_cost"]
    assert names[-1] == "uncertainty_information"


def test_table2_numbers_bold_and_dashes(report):
    out, text = report
    table = pd.read_csv(out / "table2.csv").set_index(["estimator", "perturbation", "uncertainty"])
    expected = {  # by hand from STUDY: (u(sigma_max) - u(0)) / (u(0) * (sigma_max - sigma_0))
        ("mc", "observation_noise", "u_feat"): (3.0, 9.0, 1.0),        # episode means (2, 4) -> 3; (7, 11) -> 9
        ("mc", "observation_noise", "u_ep_heading"): (0.3, 0.9, 1.0),
        ("mc", "observation_noise", "u_al_heading"): (0.5, 0.5, 0.0),
        ("mc", "observation_noise", "u_al_speed"): (6.0, 18.0, 1.0),
        ("ensemble", "observation_noise", "u_feat"): (1.0, 2.0, 0.5),
        ("ensemble", "observation_noise", "u_ep_heading"): (0.1, 0.2, 0.5),
        ("ensemble", "observation_noise", "u_al_heading"): (0.5, 1.0, 0.5),
        ("ensemble", "observation_noise", "u_al_speed"): (2.0, 4.0, 0.5),
        ("ensemble", "observation_noise", "u_ep_speed"): (1.0, 1.0, 0.0),
        ("mc", "more_humans", "u_feat"): (2.0, 4.5, 0.25),
    }
    for key, (u0, u_max, value) in expected.items():
        row = table.loc[key]
        assert row["u_sigma0"] == pytest.approx(u0) and row["u_sigma_max"] == pytest.approx(u_max), key
        assert row["sensitivity"] == pytest.approx(value, abs=1e-12), key
    zero = table.loc[("mc", "observation_noise", "u_ep_speed")]
    assert np.isnan(zero["sensitivity"]) and zero["note"] == "zero baseline"
    assert table.loc[("mc", "observation_noise", "u_feat"), "paper"] == 1.84
    assert table.loc[("mc", "observation_noise", "u_feat"), "episodes_sigma0"] == 2

    markdown = (out / "table2.md").read_text()
    header = markdown.splitlines()[0]
    assert header.startswith("| Uncertainty | Observation noise: MC | Observation noise: Ens | More humans: MC |")
    rows = {row[0]: row[1:] for row in _cells(markdown)}
    # columns: obs MC, obs Ens, more humans MC, more humans Ens (not recorded)
    assert rows["Predictive feature"] == ["**1.00**", "0.50", "0.25", "n/a"]   # one defined value: no bold
    assert rows["Aleatoric heading"] == ["0.00", "**0.50**", "0.00", "n/a"]
    assert rows["Aleatoric speed"] == ["**1.00**", "0.50", "0.25", "n/a"]
    assert rows["Epistemic heading"] == ["**1.00**", "0.50", "0.25", "n/a"]
    assert rows["Epistemic speed"] == ["—", "0.00", "—", "n/a"]                 # u(0) = 0: undefined
    assert "## Table 2" in text and markdown.strip() in text and "u_σ(0) = 0" in text


def test_table2_claims_with_magnitudes_and_intervals(report):
    out, text = report
    claims = pd.read_csv(out / "table2_claims.csv")
    assert {"claim", "test", "estimate", "low", "high", "verdict"} <= set(claims.columns)
    mc = claims[claims["claim"].str.startswith("MC-dropout responds")].set_index("uncertainty")
    # observation noise, 2 paired episodes: |ΔU/Δσ| MC - ensemble = 1 - 0.5 (u_feat, u_al_speed, u_ep_heading) and
    # 0 - 0.5 (u_al_heading; u_al_heading is flat for MC, a constant 0.5 -> 1.0 for the ensemble); u_ep_speed: MC's
    # u(0) = 0, undefined, not compared
    assert sorted(mc.index) == ["u_al_heading", "u_al_speed", "u_ep_heading", "u_feat"]
    assert mc["estimate"].to_dict() == pytest.approx({"u_feat": 0.5, "u_al_speed": 0.5, "u_ep_heading": 0.5,
                                                      "u_al_heading": -0.5})
    assert mc.loc["u_al_heading", "verdict"] == "does not hold"  # the ensemble responds more, in every resample
    assert np.allclose(mc["confidence"], 1 - 0.05 / 4)  # Bonferroni over the 4 cells compared
    assert "cannot tell in" in text and "ensemble larger in 1 of the 4 cells" in text
    assert "## Table 2 claims" in text and "over episodes for ONE acting policy" in text
    assert (out / "table2_claims.md").read_text().startswith("| Claim (paper) | Test | Scope |")


def test_uncertainty_vs_strength_curves_and_figure(report):
    out, text = report
    curves = pd.read_csv(out / "uncertainty_vs_strength.csv")
    mc = curves[(curves["estimator"] == "mc") & (curves["perturbation"] == "observation_noise")
                & (curves["uncertainty"] == "u_ep_heading")].set_index("strength")
    assert mc["u_mean"].tolist() == pytest.approx([0.3, 0.5, 0.9])
    assert mc["u_normalised"].tolist() == pytest.approx([1.0, 5 / 3, 3.0])
    assert mc["collision_rate"].tolist() == pytest.approx([0.0, 0.5, 0.5])
    assert mc["episodes"].tolist() == [2, 2, 2]
    flat = curves[(curves["estimator"] == "mc") & (curves["uncertainty"] == "u_ep_speed")]
    assert flat["u_normalised"].isna().all()  # u(0) = 0: no normalised curve
    assert (out / "uncertainty_vs_strength.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "<svg" in (out / "uncertainty_vs_strength.svg").read_text()[:2000]
    assert "![uncertainty vs strength](uncertainty_vs_strength.png)" in text


def test_feature_uncertainty_at_critical_steps(report):
    out, text = report
    critical = pd.read_csv(out / "feature_uncertainty_collisions.csv")
    got = {(r.estimator, r.perturbation, r.strength, r.episode): (bool(r.collided), r.value)
           for r in critical.itertuples()}
    assert got == {  # by hand: last row of collision episodes, row of the minimum gap otherwise
        ("mc", "observation_noise", 0.0, 0): (False, 0.2), ("mc", "observation_noise", 0.0, 1): (False, 0.3),
        ("mc", "observation_noise", 1.0, 0): (False, 0.4), ("mc", "observation_noise", 1.0, 1): (True, 0.5),
        ("mc", "observation_noise", 2.0, 0): (False, 0.7), ("mc", "observation_noise", 2.0, 1): (True, 0.9),
        ("ensemble", "observation_noise", 0.0, 0): (False, 0.02),
        ("ensemble", "observation_noise", 0.0, 1): (True, 0.03),
        ("ensemble", "observation_noise", 1.0, 0): (False, 0.04),
        ("ensemble", "observation_noise", 2.0, 0): (False, 0.06),
        ("ensemble", "observation_noise", 2.0, 1): (True, 0.08),
        ("mc", "more_humans", 2.0, 0): (False, 1.0), ("mc", "more_humans", 7.0, 0): (True, 1.2),
    }
    # summary row: 2 collisions of 6 episodes, medians 0.7 (0.5, 0.9) and 0.35 (0.2, 0.3, 0.4, 0.7)
    assert "| MC-dropout | Observation noise | 2 / 6 | 0.7 | 0.35 |" in text
    assert (out / "feature_uncertainty_collisions.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "<svg" in (out / "feature_uncertainty_collisions.svg").read_text()[:2000]


def test_table3_prevented_collisions(report):
    out, text = report
    table = pd.read_csv(out / "table3.csv").set_index(["estimator", "variant", "column"])
    expected = {  # (mean, std ddof=0, repeats with C_none > 0, repeats) from the comments in SAFETY
        ("mc", "paper", "observation_noise"): ((200 / 3 + 100) / 2, (100 - 200 / 3) / 2, 2, 2),
        ("mc", "calibrated", "observation_noise"): ((100 / 3 + 0) / 2, (100 / 3) / 2, 2, 2),
        ("mc", "paper", "heading_noise"): (25.0, 25.0, 2, 2),
        ("mc", "paper", "speed_noise"): (100.0, 0.0, 1, 2),
        ("mc", "paper", "action_noise"): ((200 / 3 + 0) / 2, (200 / 3) / 2, 2, 2),  # pooled: 3 -> 1, 1 -> 1
        ("ensemble", "paper", "observation_noise"): (100 / 3, 100 / 3, 2, 2),
    }
    for key, (mean, std, defined, repeats) in expected.items():
        row = table.loc[key]
        assert row["prevented_mean"] == pytest.approx(mean) and row["prevented_std"] == pytest.approx(std), key
        assert (row["repeats_defined"], row["repeats"]) == (defined, repeats), key
    assert table.loc[("mc", "paper", "observation_noise"), "collisions_none"] == 4  # 3 + 1, sigma(0) left out
    undefined = table.loc[("mc", "paper", "faster_humans")]
    assert undefined["repeats_defined"] == 0 and np.isnan(undefined["prevented_mean"])
    assert table.loc[("mc", "paper", "observation_noise"), "paper_mean"] == 100
    assert ("ensemble", "paper", "action_noise") not in table.index  # the ensemble ran no action noise

    markdown = (out / "table3.md").read_text().split("\n\n")[0]  # the paper's columns (the next test: ours)
    assert markdown.splitlines()[0] == ("| Approach | Thresholds | Observation noise | Action noise (heading + speed) "
                                        "| Velocity (faster humans) |")
    rows = _cells(markdown)
    assert rows[1] == ["MC-dropout", "calibrated thresholds", "16.7 ± 16.7", "n/a", "—"]
    assert rows[3] == ["Ensemble", "paper thresholds", "33.3 ± 33.3", "n/a", "n/a"]
    assert rows[4][:3] == ["Ensemble", "*paper's Table III*", "*79 ± 11*"]
    assert "## Table 3" in text and "Warning" not in text


def test_cost_of_the_safety_layer(report):
    out, text = report
    table = pd.read_csv(out / "table3_cost.csv").set_index(["estimator", "variant"])
    paper = table.loc[("ensemble", "paper")]
    # perturbed paper episodes: 6 goals (length 10, 1 fallback step) + 2 collisions (length 6, 3 fallback steps)
    assert paper["episodes_perturbed"] == 8 and paper["episodes_unperturbed"] == 2
    assert paper["activation_pct"] == pytest.approx(100 * 12 / 72)
    # unperturbed: a goal (10 steps, 1 fallback) and a time-out (20 steps, 5 fallback)
    assert paper["false_activation_pct"] == pytest.approx(100 * 6 / 30)
    assert paper["success_pct_perturbed"] == pytest.approx(75.0)
    assert paper["collision_pct_perturbed"] == pytest.approx(25.0)
    assert paper["success_pct_unperturbed"] == pytest.approx(50.0)
    assert paper["collision_pct_unperturbed"] == pytest.approx(0.0)
    assert paper["time_to_goal_perturbed"] == pytest.approx((4 * 3.0 + 2 * 3.5) / 6)
    assert paper["time_to_goal_unperturbed"] == pytest.approx(2.5)
    none = table.loc[("ensemble", "none")]
    assert np.isnan(none["activation_pct"]) and np.isnan(none["false_activation_pct"])
    assert none["collision_pct_perturbed"] == pytest.approx(50.0)
    assert none["time_to_goal_perturbed"] == pytest.approx((3 * 3.0 + 3.5) / 4)
    assert list(table.index) == [("mc", "none"), ("mc", "paper"), ("mc", "calibrated"), ("ensemble", "none"),
                                 ("ensemble", "paper")]
    assert "| Ensemble | paper thresholds | 8 / 2 | 16.67 | 20.00 | 75.0 / 50.0 | 25.0 / 0.0 | 3.17 / 2.50 |" in text
    assert "| Ensemble | none (plain policy) | 8 / 2 | – | – | 50.0 / 100.0 | 50.0 / 0.0 | 3.12 / 2.50 |" in text
    assert "## Calibrated safety thresholds" in text and "| MC-dropout | calibrated | 0.05 | 0.25 | 1 | 0.25 |" in text


def test_sections_skip_missing_records_and_unfinished_units(tmp_path):
    page = build_report(_run_dir(tmp_path / "table2", safety=False, calibration=False))
    text = page.read_text()
    assert "## Table 2" in text and "Fig. 6" in text and "Table 3" not in text and "safety layer" not in text
    assert not (page.parent / "table3.csv").exists()

    page = build_report(_run_dir(tmp_path / "table3", study=False))
    text = page.read_text()
    assert "## Table 3" in text and "## Table 2" not in text and "Fig. 5" not in text
    assert not (page.parent / "table2.csv").exists()

    text = build_report(_run_dir(tmp_path / "empty", study=False, safety=False, calibration=False)).read_text()
    assert "No study, safety or calibration records yet." in text

    # a planned unit that is not finished: its records are left out (the header lists it as partial)
    unit = {"id": "study/ensemble/observation_noise", "kind": "study", "params": {}, "deps": []}
    page = build_report(_run_dir(tmp_path / "partial", safety=False, calibration=False, units=[unit]))
    text = page.read_text()
    assert "Partial results" in text and "study/ensemble/observation_noise" in text
    table = pd.read_csv(page.parent / "table2.csv")
    assert set(table["estimator"]) == {"mc"}


def test_unpaired_seeds_are_flagged(tmp_path):
    root = _run_dir(tmp_path / "run", study=False, calibration=False)
    path = root / "safety" / "ensemble" / "observation_noise" / "episodes.parquet"
    frame = pd.read_parquet(path)
    frame.loc[frame["variant"] == "paper", "seed"] += 7
    write_table_atomic(frame, path)
    text = build_report(root).read_text()
    assert "**Warning**" in text and "not paired" in text


def test_calibrated_thresholds_switched_off_in_json_show_as_infinity(tmp_path):
    root = _run_dir(tmp_path / "run", study=False, safety=False)
    path = root / "calibrate" / "mc" / "calibration.json"
    data = json.loads(path.read_text())
    data["thresholds"] = {**data["thresholds"], "lambda_ep": None, "proximity": "closing-speed"}  # how inf is saved
    path.write_text(json.dumps(data))
    text = build_report(root).read_text()
    assert "| MC-dropout | calibrated | ∞ | 0.25 | 1 | 0.25 | closing-speed | 0 | 0.8 | 0.01 |" in text


def test_table3_reports_each_sensing_against_the_same_plain_runs():
    from socnav.paper.uncertainty.table3 import cost_frame, cost_markdown, prevented_frame, prevented_markdown

    frame = _safety("mc", "observation_noise")
    frame["sensing"] = np.where(frame["variant"] == "none", "", "perceived")
    # the layer reading the true state prevents every perturbed collision of the same episodes
    true = frame[frame["variant"] == "paper"].assign(sensing="true")
    true.loc[true["strength"] > 0, "outcome"] = G
    both = pd.concat([frame, true], ignore_index=True)
    table = prevented_frame(both).set_index(["estimator", "variant", "sensing", "column"])
    perceived = table.loc[("mc", "paper", "perceived", "observation_noise")]
    assert perceived["prevented_mean"] == pytest.approx((200 / 3 + 100) / 2)  # as without the sensing column
    row = table.loc[("mc", "paper", "true", "observation_noise")]
    assert (row["prevented_mean"], row["prevented_std"], row["collisions_none"]) == (100.0, 0.0, 4)
    assert ("mc", "calibrated", "true", "observation_noise") not in table.index
    rows = _cells(prevented_markdown(prevented_frame(both)))
    assert [r[1] for r in rows] == ["paper thresholds, perceived", "paper thresholds, true state",
                                    "calibrated thresholds, perceived", "*paper's Table III*"]
    assert rows[1][2] == "100.0 ± 0.0"
    cost = cost_frame(both)
    assert cost[["variant", "sensing"]].values.tolist() == [["none", ""], ["paper", "perceived"], ["paper", "true"],
                                                            ["calibrated", "perceived"]]
    assert cost.loc[2, "collision_pct_perturbed"] == 0.0
    assert "| MC-dropout | paper thresholds, true state |" in cost_markdown(cost)
    # records without a sensing column read as perceived, and their labels name no sensing
    without = prevented_frame(frame.drop(columns="sensing"))
    assert set(without["sensing"]) == {"perceived"}
    assert _cells(prevented_markdown(without))[0][1] == "paper thresholds"


def test_unpaired_groups_compares_each_sensing_with_the_plain_policy():
    """Two sensings of one variant on the plain policy's seeds are paired; a run on other seeds is not."""
    import pandas as pd

    from socnav.paper.uncertainty.table3 import unpaired_groups

    def rows(variant, sensing, seeds):
        return [{"estimator": "mc", "perturbation": "heading_noise", "strength": 1.0, "repeat": 0,
                 "variant": variant, "sensing": sensing, "seed": seed} for seed in seeds]

    paired = pd.DataFrame(rows("none", "perceived", [0, 1, 2]) + rows("paper", "perceived", [0, 1, 2])
                          + rows("paper", "true", [2, 1, 0]))
    assert unpaired_groups(paired) == 0
    shifted = pd.DataFrame(rows("none", "perceived", [0, 1, 2]) + rows("paper", "perceived", [0, 1, 2])
                           + rows("paper", "true", [0, 1, 3]))
    assert unpaired_groups(shifted) == 1


# ------------------------------------------------------------------------------------------------ Table 3 ablation

def test_table3_shows_each_of_the_papers_columns_once(report):
    out, text = report
    paper_table, own_table = (out / "table3.md").read_text().strip().split("\n\n")
    assert paper_table.splitlines()[0] == ("| Approach | Thresholds | Observation noise | Action noise (heading + "
                                           "speed) | Velocity (faster humans) |")
    rows = _cells(paper_table)
    assert rows[0] == ["MC-dropout", "paper thresholds", "83.3 ± 16.7", "33.3 ± 33.3", "—"]
    assert rows[2] == ["MC-dropout", "*paper's Table III*", "*100 ± 0*", "*6 ± 5*", "*56 ± 2*"]
    assert paper_table.count("*6 ± 5*") == 1  # the paper's action noise, compared once (heading + speed pooled)
    assert own_table.splitlines()[0] == ("| Approach | Thresholds | Heading noise alone (ours) | "
                                         "Speed noise alone (ours) |")
    assert _cells(own_table)[0] == ["MC-dropout", "paper thresholds", "25.0 ± 25.0", "100.0 ± 0.0 (1 of 2)"]
    assert "paper's Table III" not in own_table and "Our own columns" in text


def test_mcnemar_exact_by_hand():
    from scipy.stats import binomtest

    from socnav.paper.uncertainty.ablation import mcnemar_exact

    # 10 discordant episodes, all won: pi's Clopper-Pearson lower end is (alpha / 2) ** (1 / 10), the upper 1
    low, high, p = mcnemar_exact(10, 0, 0.95)
    assert low == pytest.approx(10 * (2 * 0.025 ** 0.1 - 1)) and low == pytest.approx(3.8301, abs=1e-4)
    assert high == 10 and p == pytest.approx(2 / 2 ** 10)
    assert mcnemar_exact(0, 10, 0.95) == pytest.approx((-10, -low, p))  # the mirror image
    assert mcnemar_exact(0, 0, 0.95) == (0.0, 0.0, 1.0)  # the rules decided alike in every episode
    low, high, p = mcnemar_exact(3, 3, 0.95)
    assert low == pytest.approx(-high) and p == 1.0
    assert mcnemar_exact(7, 2, 0.95)[2] == pytest.approx(binomtest(7, 9, 0.5).pvalue)


def _ablation_records() -> pd.DataFrame:
    """Hand-made ablation records, true-state sensing, observation noise: 20 perturbed episodes (seeds 0-19) and 4
    unperturbed ones (seeds 100-103), 10 steps each. Collisions (perturbed): plain 0-14 (15); proximity-only
    0-11; gated (MC-dropout's paper rule, calibrated) 0-1; uncertainty-only 0-14; the paper's thresholds 0-11.
    At the 2 % trade-off budget: proximity-only 0-13, gated 0-5."""
    collided = {("mc", "none", "", np.nan): range(15), ("none", "none", "", np.nan): range(15),
                ("none", "calibrated", "proximity-only", 0.05): range(12),
                ("none", "calibrated", "proximity-only", 0.02): range(14),
                ("mc", "calibrated", "paper", 0.05): range(2), ("mc", "calibrated", "paper", 0.02): range(6),
                ("mc", "calibrated", "uncertainty-only", 0.05): range(15), ("mc", "paper", "paper", np.nan): range(12)}
    fallback = {"proximity-only": 2, "paper": 1, "uncertainty-only": 3, "": 0}  # per unperturbed episode
    rows = []
    for (estimator, variant, rule, budget), hits in collided.items():
        for strength, seeds in ((0.0, range(100, 104)), (1.0, range(20))):
            for seed in seeds:
                hit = strength > 0 and seed in hits
                steps = fallback[rule] if variant != "paper" else 0
                rows.append({"estimator": estimator, "perturbation": "observation_noise", "strength": strength,
                             "repeat": 0, "variant": variant, "sensing": "" if variant == "none" else "true",
                             "rule": rule, "budget": budget, "seed": seed, "outcome": "collision" if hit else "goal",
                             "length": 10, "time_to_goal": np.nan if hit else 2.5, "duration": 2.5,
                             "fallback_steps": steps, "proximity_steps": 4 if variant != "none" else 0,
                             # the gated rule's uncertainty condition vetoed one of its 4 proximity firings
                             "vetoed_steps": 1 if (rule, variant) == ("paper", "calibrated") else 0,
                             # its hand-overs differ from proximity-only's in the perturbed episodes 0-6
                             "fallback_digest": "b" if rule == "paper" and strength > 0 and seed < 7 else "a"})
    return pd.DataFrame(rows)


def test_ablation_compares_every_rule_with_proximity_only_episode_by_episode():
    from socnav.paper.uncertainty.ablation import ablation_records, decisions_frame, paired_frame

    view = ablation_records(_ablation_records(), "true", 0.05)
    paired = paired_frame(view).set_index(["estimator", "row", "column"])
    assert set(paired.index) == {("mc", row, column) for row in ("paper", "uncertainty-only", "calibrated")
                                 for column in ("all", "observation_noise", "unperturbed")}
    unperturbed = paired.loc[("mc", "calibrated", "unperturbed")]  # no collision there: nothing to tell apart
    assert (unperturbed["episodes"], unperturbed["collisions_none"], unperturbed["difference"]) == (4, 0, 0)
    gated = paired.loc[("mc", "calibrated", "all")]
    # proximity-only collides in 0-11, the gated rule in 0-1: it alone prevents 2-11 (10), never the reverse
    assert (gated["row_only_prevented"], gated["reference_only_prevented"], gated["difference"]) == (10, 0, 10)
    assert gated["collisions_none"] == 15 and gated["difference_pct"] == pytest.approx(100 * 10 / 15)
    # Bonferroni over the 3 rows compared: alpha = 0.05 / 3; by hand, 10 of 10 won -> pi >= (alpha / 2) ** (1 / 10)
    alpha = 0.05 / 3
    assert gated["comparisons"] == 3 and gated["confidence"] == pytest.approx(1 - alpha)
    assert gated["low_pct"] == pytest.approx(100 / 15 * 10 * (2 * (alpha / 2) ** 0.1 - 1))
    assert gated["high_pct"] == pytest.approx(100 * 10 / 15) and gated["verdict"] == "holds"
    assert gated["p_adjusted"] == pytest.approx(3 * 2 / 2 ** 10)
    only = paired.loc[("mc", "uncertainty-only", "all")]  # lost 3 (12-14), won none: n = 3 is too few to tell
    assert (only["row_only_prevented"], only["reference_only_prevented"]) == (0, 3)
    assert only["high_pct"] == pytest.approx(100 / 15 * 3 * (1 - 2 * (alpha / 2) ** (1 / 3)))
    assert only["verdict"] == "cannot tell at this budget" and only["p_value"] == pytest.approx(0.25)
    same = paired.loc[("mc", "paper", "all")]  # the paper's thresholds collide exactly where proximity-only does
    assert (same["difference"], same["low_pct"], same["high_pct"]) == (0, 0.0, 0.0)
    assert same["verdict"] == "cannot tell at this budget"
    # per column: Bonferroni over rows x columns (here one column)
    assert paired.loc[("mc", "calibrated", "observation_noise"), "comparisons"] == 6

    decisions = decisions_frame(view).set_index(["estimator", "row"])
    gated = decisions.loc[("mc", "calibrated")]
    assert gated["false_activation_pct"] == pytest.approx(10.0)  # 1 of 10 steps in each unperturbed episode
    assert gated["vetoed_pct"] == pytest.approx(25.0) and gated["vetoed_steps"] == 24
    assert (gated["episodes_other_decisions"], gated["paired_episodes"]) == (7, 24)
    assert decisions.loc[("none", "proximity-only"), "false_activation_pct"] == pytest.approx(20.0)
    assert np.isnan(decisions.loc[("mc", "uncertainty-only"), "vetoed_pct"])  # no proximity terms to veto


def test_ablation_and_tradeoff_sections(tmp_path):
    records = _ablation_records()
    root = _run_dir(tmp_path / "run", study=False, safety=False, calibration=False)
    resolved = {"experiment": {"name": "unc", "kind": "uncertainty", "budget": "quick",
                               "evaluation": {"seed": 3_000_000, "episodes": 20},
                               "safety": {"false_activation_budget": 0.05, "repeats": 1, "calibration_episodes": 60,
                                          "ablation_sensing": "true"}}}
    (root / "resolved.json").write_text(json.dumps(resolved))
    for estimator in ("mc", "none"):
        write_table_atomic(records[records["estimator"] == estimator],
                           root / "safety" / estimator / "observation_noise" / "episodes.parquet")
    page = build_report(root)
    text, out = page.read_text(), page.parent
    # Table 3 and its cost: the main rows only (no ablation rule, no trade-off budget, no estimator-free unit)
    table3 = pd.read_csv(out / "table3.csv")
    assert set(zip(table3["estimator"], table3["variant"], strict=True)) == {("mc", "paper"), ("mc", "calibrated")}
    assert table3.set_index("variant").loc["calibrated", "collisions_variant"] == 2  # budget 5 %, not 2 %
    assert "Warning" not in text  # every rule and budget played the plain policy's seeds
    assert "seeds 3,000,000–3,000,019" in text and "held out" in text and "not held out" not in text
    cost = pd.read_csv(out / "table3_cost.csv")
    assert list(cost["variant"]) == ["none", "paper", "calibrated"]
    assert cost.loc[2, "false_activation_pct"] == pytest.approx(10.0)
    # the ablation: a row per rule, proximity-only the reference
    assert "## Table 3 ablation" in text
    rows = {(r[0], r[1]): r for r in _cells((out / "table3_ablation.md").read_text())}
    gated = rows[("Paper's rule (c_ep ∨ c_feat) ∧ c_prox ∧ c_ap, calibrated: uncertainty-gated", "MC-dropout")]
    assert gated[3:7] == ["10.00", "25.0 (24 of 96)", "7 of 24", "+66.7 [+15.9, +66.7] (10 vs 0)"]
    assert gated[7] == "holds"
    assert rows[("Proximity only: c_prox ∧ c_ap (calibrated)", "–")][5] == "reference"
    # the trade-off: per rule and budget, measured false activation and prevented share
    curve = pd.read_csv(out / "table3_tradeoff.csv")
    points = {(r.estimator, r.thresholds, r.budget if r.budget == r.budget else None):
              (r.false_activation_pct, r.prevented_pct) for r in curve.itertuples()}
    assert points[("none", "calibrated", 0.02)] == pytest.approx((20.0, 100 / 15))
    assert points[("none", "calibrated", 0.05)] == pytest.approx((20.0, 100 * 3 / 15))
    assert points[("mc", "calibrated", 0.02)] == pytest.approx((10.0, 100 * 9 / 15))
    assert points[("mc", "paper", None)] == pytest.approx((0.0, 100 * 3 / 15))
    # one budget: no curve
    assert ("mc", "uncertainty-only") not in set(zip(curve["estimator"], curve["rule"], strict=True))
    # a trade-off budget played on the first repeat only: every point of the curve on that repeat alone
    from socnav.paper.uncertainty.tradeoff import tradeoff_frame

    second = records[records["budget"] != 0.02].assign(repeat=1)
    second.loc[second["outcome"] == "collision", "outcome"] = "goal"  # a repeat the curve must not see
    both = tradeoff_frame(pd.concat([records, second], ignore_index=True), "true")
    pd.testing.assert_frame_equal(both, tradeoff_frame(records, "true"))
    assert (out / "table3_tradeoff.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "<svg" in (out / "table3_tradeoff.svg").read_text()[:2000]


def test_calibration_table_names_the_rule_and_hides_what_it_ignores(tmp_path):
    root = _run_dir(tmp_path / "run", study=False, safety=False)
    for name, data in (("calibrate-true/proximity-only/calibration.json",
                        {"thresholds": {"lambda_ep": 0.0, "lambda_feat": 0.0, "lambda_prox": 0.4, "beta1": 1.0,
                                        "proximity": "closing-speed", "sensing": "true", "hold_steps": 1,
                                        "conditions": "proximity-only"}, "estimator": "none",
                         "conditions": "proximity-only", "sensing": "true", "false_activation_budget": 0.05,
                         "prevented_fraction": 0.9, "false_activation_rate": 0.03}),
                       ("calibrate-true/mc-uncertainty-only/calibration-budget0.02.json",
                        {"thresholds": {"lambda_ep": 0.2, "lambda_feat": None, "lambda_prox": 1000.0, "beta1": 0.0,
                                        "conditions": "uncertainty-only"}, "estimator": "mc",
                         "conditions": "uncertainty-only", "sensing": "true", "false_activation_budget": 0.02,
                         "prevented_fraction": 0.5, "false_activation_rate": 0.01})):
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(data))
    text = build_report(root).read_text()
    assert ("| – | calibrated, proximity only (true state) | – | – | 0.4 | 1 | closing-speed | 1 | 0.9 | 0.03 |"
            in text)
    assert ("| MC-dropout | calibrated, uncertainty only (true state), 2 % budget | 0.2 | ∞ | – | – |" in text)
    assert "| MC-dropout | calibrated | 0.05 | 0.25 | 1 | 0.25 |" in text  # the paper's rule as before


# ------------------------------------------------------------------------------------------------ behaviour shift

def test_behaviour_shift_is_a_column_of_ours_in_tables_2_and_3_and_not_in_the_papers_claims(tmp_path):
    """The behaviour shift (strength 0: the humans as trained, 1: social force humans) gets its own "(ours)"
    columns from the registry; the paper's claims and columns stay as they were."""
    root = _run_dir(tmp_path / "run")
    for estimator in ("mc", "ensemble"):
        steps = _steps(estimator, "observation_noise")
        steps = steps[steps["strength"] <= 1.0].assign(perturbation="behaviour_shift")
        write_table_atomic(steps, root / "study" / estimator / "behaviour_shift" / "steps.parquet")
    write_table_atomic(_safety("mc", "heading_noise").assign(perturbation="behaviour_shift"),
                       root / "safety" / "mc" / "behaviour_shift" / "episodes.parquet")
    page = build_report(root)
    text, out = page.read_text(), page.parent
    header = (out / "table2.md").read_text().splitlines()[0]
    assert header.endswith("| More humans: MC | More humans: Ens | Behaviour shift (ours): MC | "
                           "Behaviour shift (ours): Ens |")
    table2 = pd.read_csv(out / "table2.csv").set_index(["estimator", "perturbation", "uncertainty"])
    row = table2.loc[("mc", "behaviour_shift", "u_feat")]  # episode means (2, 4) -> 3; (5, 5) -> 5
    assert (row["sigma0"], row["sigma_max"]) == (0.0, 1.0) and row["sensitivity"] == pytest.approx(2 / 3)
    assert np.isnan(row["paper"])
    claims = pd.read_csv(out / "table2_claims.csv")
    assert "behaviour_shift" not in set(claims["perturbation"]) and "the paper claims nothing about them" in text
    paper_table, own_table = (out / "table3.md").read_text().strip().split("\n\n")
    assert "Behaviour shift" not in paper_table
    assert own_table.splitlines()[0] == ("| Approach | Thresholds | Heading noise alone (ours) | "
                                         "Speed noise alone (ours) | Behaviour shift (ours) |")
    assert _cells(own_table)[0] == ["MC-dropout", "paper thresholds", "25.0 ± 25.0", "100.0 ± 0.0 (1 of 2)",
                                    "25.0 ± 25.0"]
    assert "no behaviour shift" in text
    curves = pd.read_csv(out / "uncertainty_vs_strength.csv")
    assert set(curves.loc[curves["perturbation"] == "behaviour_shift", "strength"]) == {0.0, 1.0}


def test_vetoes_are_counted_per_setting_with_the_unperturbed_episodes_together():
    from socnav.paper.uncertainty.ablation import vetoes_frame, vetoes_markdown

    rows = []
    for perturbation, strength, proximity, vetoed in [("observation_noise", 0.0, 10, 3),
                                                      ("observation_noise", 2.0, 8, 0),
                                                      ("more_humans", 2.0, 5, 2), ("more_humans", 7.0, 4, 1)]:
        for variant in ("calibrated", "proximity-only", "none"):
            rows.append({"estimator": "mc" if variant == "calibrated" else "none", "variant": variant,
                         "perturbation": perturbation, "strength": strength, "proximity_steps": proximity,
                         "vetoed_steps": vetoed if variant == "calibrated" else 0})
    vetoes = vetoes_frame(pd.DataFrame(rows))
    assert vetoes["setting"].tolist() == ["unperturbed", "more_humans 7", "observation_noise 2"]
    assert vetoes["proximity_steps"].tolist() == [15, 4, 8]  # obs 0 and N 2 are both unperturbed: 10 + 5
    assert vetoes["vetoed_pct"].tolist() == pytest.approx([100 * 5 / 15, 25.0, 0.0])
    assert "| MC-dropout, calibrated | 33.3 | 25.0 | 0.0 |" in vetoes_markdown(vetoes)


def test_a_column_of_ours_does_not_change_the_pooled_comparison():
    from socnav.paper.uncertainty.ablation import paper_column_kinds

    groups = paper_column_kinds(["behaviour_shift", "observation_noise", "heading_noise", "speed_noise"])
    assert groups["all"] == ["observation_noise", "heading_noise", "speed_noise"]  # the paper's types only
    assert groups["behaviour_shift"] == ["behaviour_shift"]  # reported on its own
    assert groups["action_noise"] == ["heading_noise", "speed_noise"]
