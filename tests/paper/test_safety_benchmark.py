"""The safety-layer benchmark: its plan, its pooled table by hand, the paired comparison against proximity-only, and
verdicts whose error rate is shown by simulating the null (and whose power is shown on a real difference)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from socnav.experiments.spec import ExperimentError, load_experiment, parse_experiment, plan_units
from socnav.paper.safety_benchmark.benchmark import BenchmarkSetup, paired_against, summarize_layers
from socnav.paper.safety_benchmark.units import benchmark_markdown, seed_differences, verdicts

CONFIG = "configs/experiments/safety_benchmark.yaml"


def _episodes(layers: dict[str, dict[str, list[int]]], seed: int = 0, lengths: int = 10) -> pd.DataFrame:
    """Episode rows: layer -> world -> collided flags (one per episode); worlds named `group=strength`, `unperturbed`
    or a shift; every layer falls back on one step of each unperturbed episode."""
    rows = []
    for layer, worlds in layers.items():
        for world, flags in worlds.items():
            group = "unperturbed" if world == "unperturbed" else "shift" if "=" not in world else world.split("=")[0]
            for episode, collided in enumerate(flags):
                rows.append({"train_seed": seed, "world": world, "group": group, "layer": layer,
                             "budget": 0.0 if layer == "plain" else 0.05, "fallback": "" if layer == "plain"
                             else "cautious", "episode": episode, "collided": bool(collided),
                             "goal": not collided, "length": lengths, "fallback_at_end": False,
                             "fallback_steps": 0 if layer == "plain" else int(world == "unperturbed")})
    return pd.DataFrame(rows)


def test_the_plan_trains_then_benchmarks_each_seed():
    experiment = load_experiment(CONFIG, "check")
    units = plan_units(experiment)
    trains = [unit for unit in units if unit.kind == "train"]
    benchmarks = [unit for unit in units if unit.kind == "safety_benchmark"]
    assert len(trains) == len(benchmarks) == 2
    assert [unit.deps for unit in benchmarks] == [(train.id,) for train in trains]
    assert benchmarks[0].params["budgets"] == [0.05]
    quick = plan_units(load_experiment(CONFIG, "quick"))
    assert next(u for u in quick if u.kind == "safety_benchmark").params["budgets"] == [0.01, 0.02, 0.05, 0.1]
    assert len([u for u in quick if u.kind == "safety_benchmark"]) == 20


def test_unknown_trigger_in_a_config_names_the_closest():
    import yaml

    data = yaml.safe_load(Path(CONFIG).read_text())
    data["safety"]["triggers"] = ["conformall"]
    with pytest.raises(ExperimentError, match="did you mean 'conformal'"):
        parse_experiment(data)


def test_replayed_pedestrians_are_a_held_out_shift_when_files_are_given(tmp_path):
    import yaml

    from socnav.paper.safety_benchmark.benchmark import replay_shift

    rows = [(10 * j, ped, 0.5 * j - 3.0, float(ped)) for j in range(12) for ped in (1, 2)]
    recording = tmp_path / "scene.txt"
    recording.write_text("".join(f"{frame}\t{ped:.1f}\t{x:.2f}\t{y:.2f}\n" for frame, ped, x, y in sorted(rows)))
    data = yaml.safe_load(Path(CONFIG).read_text())
    without = [u for u in plan_units(parse_experiment(data)) if u.kind == "safety_benchmark"]
    assert "replay_files" not in without[0].params  # the units as before the shift existed: runs resume
    data["safety"]["replay_files"] = [str(recording)]
    units = [u for u in plan_units(parse_experiment(data)) if u.kind == "safety_benchmark"]
    assert units[0].params["replay_files"] == [str(recording.resolve())]
    setup = BenchmarkSetup(env={"scenario": "position_swap", "n_humans": 1},
                           shifts=replay_shift(units[0].params["replay_files"]))
    group, world = setup.worlds()["replay"]
    assert (group, world.scenario, world.humans.model) == ("shift", "replay", "replay")
    data["safety"]["replay_files"] = [str(tmp_path / "missing.txt")]
    with pytest.raises(ExperimentError, match=r"safety\.replay_files"):
        plan_units(parse_experiment(data))


def test_the_setup_holds_out_the_calibration_strengths():
    from socnav.envs.perturbations import CALIBRATION_SET

    setup = BenchmarkSetup(env={"scenario": "position_swap", "n_humans": 1})
    for kind, strengths in setup.paper_types.items():
        assert not set(strengths) & set(CALIBRATION_SET[kind])
    groups = {group for group, _ in setup.worlds().values()}
    assert {"unperturbed", "shift"} <= groups


def test_pooled_table_by_hand():
    episodes = _episodes({
        "plain": {"unperturbed": [1, 0, 0, 0], "heading_noise=1": [1, 1, 1, 1], "corridor": [1, 1, 0, 0]},
        "proximity-only": {"unperturbed": [0, 0, 0, 0], "heading_noise=1": [1, 1, 0, 0], "corridor": [1, 0, 0, 0]},
        "time-to-collision": {"unperturbed": [0, 0, 0, 1], "heading_noise=1": [0, 0, 0, 0], "corridor": [0, 0, 0, 0]},
    })
    table = summarize_layers(episodes).set_index("layer")
    assert table.attrs["plain_collisions_paper_types"] == 4
    assert table.loc["proximity-only", "prevented_paper_types_pct"] == pytest.approx(50.0)
    assert table.loc["time-to-collision", "prevented_paper_types_pct"] == pytest.approx(100.0)
    assert table.loc["time-to-collision", "prevented_unperturbed_pct"] == pytest.approx(0.0)  # 1 vs 1
    assert table.loc["proximity-only", "prevented_corridor_pct"] == pytest.approx(50.0)
    # one fallback step in each 10-step unperturbed episode
    assert table.loc["time-to-collision", "false_activation_pct"] == pytest.approx(10.0)
    # paired over the paper types: 2 episodes fewer of 4 -> -0.5, both discordant pairs in its favour
    versus = paired_against(episodes, ("time-to-collision", 0.05, "cautious"), ("proximity-only", 0.05, "cautious"),
                            ["heading_noise=1"])
    assert versus["difference"] == pytest.approx(-0.5)
    assert (versus["fewer"], versus["more"]) == (2, 0)
    assert versus["p"] == pytest.approx(0.5)  # two-sided exact binomial test of 2 of 2


def test_unavoidable_collisions_are_those_the_robot_that_never_moves_suffers_too():
    episodes = _episodes({
        "plain": {"unperturbed": [0, 0], "heading_noise=1": [1, 1, 1, 0]},
        "stand-still": {"unperturbed": [0, 0], "heading_noise=1": [1, 0, 0, 1]},
        "proximity-only": {"unperturbed": [0, 0], "heading_noise=1": [1, 1, 0, 1]},
    })
    table = summarize_layers(episodes).set_index("layer")
    assert table.loc["proximity-only", "collisions_paper_types"] == 3
    assert table.loc["proximity-only", "collisions_unavoidable"] == 2  # episodes 0 and 3: stand-still hit there too
    assert table.loc["stand-still", "collisions_unavoidable"] == 2


def test_the_detectable_difference_is_found_with_the_stated_power():
    """Per-seed differences drawn with the spread a verdict measured and a true mean of minus its detectable
    difference: the one-sided t test at that Holm level rejects in about 80 % of simulated benchmarks."""
    from scipy import stats

    rng = np.random.default_rng(4)
    table = verdicts(_differences(rng, 20, 0.2, 0.15)).set_index("layer")
    sd, mde = table.loc["conformal", "sd"], table.loc["conformal", "detectable_pct"]
    assert mde > 0 and np.isfinite(mde)
    level = 0.05 / 1  # one tested row in this budget (proximity-only is the row to beat)
    draws = rng.normal(-mde, sd, size=(4000, 20))
    rejected = stats.ttest_1samp(draws, 0.0, axis=1, alternative="less").pvalue < level
    assert 0.75 <= rejected.mean() <= 0.85


def _seeded(rng: np.random.Generator, seeds: int, rate_base: float, rate_layer: float,
            episodes: int = 100) -> pd.DataFrame:
    frames = []
    for seed in range(seeds):
        base = rng.random(episodes) < rate_base
        layer = rng.random(episodes) < rate_layer
        frames.append(_episodes({"plain": {"unperturbed": [0] * 10, "faster_humans=4": list(base | layer)},
                                 "proximity-only": {"unperturbed": [0] * 10, "faster_humans=4": list(base)},
                                 "conformal": {"unperturbed": [0] * 10, "faster_humans=4": list(layer)}},
                                seed=seed))
    return pd.concat(frames, ignore_index=True)


def _differences(rng: np.random.Generator, seeds: int, rate_base: float, rate_layer: float,
                 episodes: int = 100) -> pd.DataFrame:
    """`seed_differences`' columns for a layer and proximity-only whose collisions are binomial per seed."""
    layer = 100.0 * rng.binomial(episodes, rate_layer, seeds) / episodes
    base = 100.0 * rng.binomial(episodes, rate_base, seeds) / episodes
    common = {"train_seed": np.arange(seeds), "budget": 0.05, "fallback": "cautious", "false_activation_pct": 1.0,
              "diff_pct_unperturbed": 0.0}
    return pd.concat([pd.DataFrame({**common, "layer": "conformal", "diff_pct_paper_types": layer - base}),
                      pd.DataFrame({**common, "layer": "proximity-only", "diff_pct_paper_types": 0.0})],
                     ignore_index=True)


def test_seed_differences_by_hand():
    episodes = pd.concat([
        _episodes({"plain": {"unperturbed": [0, 0], "faster_humans=4": [1, 1]},
                   "proximity-only": {"unperturbed": [0, 0], "faster_humans=4": [1, 0]},
                   "conformal": {"unperturbed": [1, 0], "faster_humans=4": [0, 0]}}, seed=0),
        _episodes({"plain": {"unperturbed": [0, 0], "faster_humans=4": [1, 1]},
                   "proximity-only": {"unperturbed": [0, 0], "faster_humans=4": [1, 1]},
                   "conformal": {"unperturbed": [0, 0], "faster_humans=4": [1, 0]}}, seed=1)])
    table = seed_differences(episodes).set_index(["train_seed", "layer"])
    assert table.loc[(0, "conformal"), "diff_pct_paper_types"] == pytest.approx(-50.0)
    assert table.loc[(1, "conformal"), "diff_pct_paper_types"] == pytest.approx(-50.0)
    assert table.loc[(0, "conformal"), "diff_pct_unperturbed"] == pytest.approx(50.0)
    assert table.loc[(0, "proximity-only"), "diff_pct_paper_types"] == 0.0
    verdict = verdicts(seed_differences(episodes)).set_index("layer")
    assert verdict.loc["conformal", "diff_pct"] == pytest.approx(-50.0)
    assert math.isnan(verdict.loc["conformal", "p_fewer"])  # no spread over two seeds: no test, no claim
    assert verdict.loc["conformal", "verdict"] == "not established"


def test_the_verdict_keeps_its_error_rate_under_the_null():
    """Layer and proximity-only equally good (same collision probability, independent episodes): over 1,000
    simulated benchmarks of 20 seeds the one-sided 5 % verdict says 'fewer collisions' in about 5 % of them."""
    rng = np.random.default_rng(0)
    trials = 1000
    claims = sum(int(verdicts(_differences(rng, 20, 0.2, 0.2)).set_index("layer").loc["conformal", "verdict"]
                     == "fewer collisions") for _ in range(trials))
    # binomial(1000, 0.05): mean 50, sd 6.9; 65 is the mean + 2.2 sd
    assert claims / trials <= 0.065


def test_the_verdict_finds_a_real_difference():
    rng = np.random.default_rng(1)
    found = sum(int(verdicts(_differences(rng, 20, 0.2, 0.1)).set_index("layer").loc["conformal", "verdict"]
                    == "fewer collisions") for _ in range(200))
    assert found / 200 >= 0.9  # 10 points fewer over 20 seeds of 100 episodes: power near 1
    table = verdicts(_differences(rng, 20, 0.2, 0.1))
    row = table[table["layer"] == "conformal"].iloc[0]
    assert row["low"] < -10.0 < row["high"] < 0  # the simulated difference: 10 % - 20 % = -10 points
    assert table.loc[table["layer"] == "proximity-only", "verdict"].iloc[0] == "(the row to beat)"


def test_markdown_with_one_policy_pairs_the_episodes(tmp_path):
    rng = np.random.default_rng(2)
    episodes = _seeded(rng, 1, 0.3, 0.05, episodes=200)
    text = benchmark_markdown(episodes, tmp_path, "one policy")
    assert "| conformal | 5% | cautious |" in text and "fewer collisions" in text
    assert (tmp_path / "safety_benchmark_tradeoff.png").stat().st_size > 0
    table = pd.read_csv(tmp_path / "safety_benchmark_verdicts.csv")
    assert math.isclose(table.loc[table["layer"] == "proximity-only", "diff_pct"].iloc[0], 0.0)


def test_one_policy_holm_family_is_every_row_of_a_budget(tmp_path):
    """With one acting policy the brake rows join the cautious rows' Holm family (as across seeds): two tested rows
    with the same raw p each get twice it."""
    flags = {"unperturbed": [0] * 10, "faster_humans=4": [1] * 8 + [0] * 12}
    fewer = {"unperturbed": [0] * 10, "faster_humans=4": [0] * 20}
    episodes = _episodes({"plain": flags, "proximity-only": flags, "conformal": fewer, "conformal/brake": fewer})
    brake = episodes["layer"] == "conformal/brake"
    episodes.loc[brake, "layer"], episodes.loc[brake, "fallback"] = "conformal", "brake"
    benchmark_markdown(episodes, tmp_path, "one policy")
    table = pd.read_csv(tmp_path / "safety_benchmark_verdicts.csv").set_index(["layer", "fallback"])
    raw = table.loc[("conformal", "cautious"), "p_fewer"]
    assert raw == pytest.approx(0.5 ** 8)  # 8 discordant pairs, all in its favour: one-sided exact binomial
    assert table.loc[("conformal", "cautious"), "p_holm"] == pytest.approx(2 * raw)
    assert table.loc[("conformal", "brake"), "p_holm"] == pytest.approx(2 * raw)


def test_a_small_benchmark_runs_end_to_end_and_resumes_from_its_calibration(tmp_path):
    """Three rows of the benchmark on a few episodes: calibrated, written, evaluated against the plain policy and
    the stand-still robot on the same episodes; a second run reads the calibrated layers back instead of
    calibrating again."""
    import socnav
    from socnav.paper.safety_benchmark.benchmark import LAYERS_FILE, load_layers, run_safety_benchmark

    pretrained_policy = socnav.load_policy("pretrained")

    setup = BenchmarkSetup(env={"scenario": "position_swap", "n_humans": 1}, calibration_episodes=3,
                           eval_episodes=4, paper_types={"faster_humans": [4.0]}, shifts={},
                           rows=("proximity-only", "time-to-collision", "conformal"), brake_rows=("conformal",))
    messages: list[str] = []
    summary = run_safety_benchmark(pretrained_policy, None, setup, tmp_path, log=messages.append)
    assert any("calibrating the rule (proximity-only)" in m for m in messages)
    assert set(summary["layer"]) == {"plain", "stand-still", "proximity-only", "time-to-collision", "conformal"}
    assert summary.loc[summary["fallback"] == "brake", "layer"].tolist() == ["conformal"]
    episodes = pd.read_csv(tmp_path / "episodes.csv")
    per_layer = episodes.groupby(["layer", "fallback"], dropna=False)["episode"].apply(lambda e: sorted(set(e)))
    assert all(ids == [0, 1, 2, 3] for ids in per_layer)  # every row plays the same episodes of each world
    layers = load_layers(tmp_path / LAYERS_FILE)
    assert [layer.name for layer in layers] == ["proximity-only", "time-to-collision", "conformal"]
    assert layers[2].decision.params["initial_quantile"] != 0.0  # fitted on the calibration episodes
    assert all(set(layer.calibration) == {"prevented_worst", "prevented_fraction", "false_activation_upper"}
               for layer in layers)  # what the calibration measured, kept for a choice made on it alone
    messages.clear()
    again = run_safety_benchmark(pretrained_policy, None, setup, tmp_path, log=messages.append)
    assert any("read from" in m for m in messages) and not any("calibrating" in m for m in messages)
    pd.testing.assert_frame_equal(again, summary)


def test_the_row_to_deploy_is_chosen_on_the_calibration_scores():
    from socnav.paper.safety_benchmark.benchmark import Layer
    from socnav.paper.safety_benchmark.units import calibration_table, deployment_choice
    from socnav.safety import Thresholds

    never = Thresholds.never()

    def layer(name, worst, mean, fallback="cautious"):
        return Layer(name, never, 0.05, fallback, {"prevented_worst": worst, "prevented_fraction": mean,
                                                   "false_activation_upper": 0.04})

    seeds = [[layer("proximity-only", 0.2, 0.5), layer("conformal", 0.5, 0.6), layer("ttc", 0.5, 0.7),
              layer("conformal", 0.9, 0.9, "brake")],
             [layer("proximity-only", 0.4, 0.5), layer("conformal", 0.7, 0.6), layer("ttc", 0.5, 0.7)]]
    table = calibration_table(seeds).set_index(["layer", "fallback"])
    # the mean of 50 and 70
    assert table.loc[("conformal", "cautious"), "calibration_prevented_worst"] == pytest.approx(60.0)
    # worst type first (conformal 60 > ttc 50), whatever the mean; the brake row is not a candidate
    assert deployment_choice(calibration_table(seeds), 0.05) == "conformal"
    assert deployment_choice(calibration_table(seeds[:1]), 0.05) == "ttc"  # tie on the worst type: the mean
    assert deployment_choice(calibration_table(seeds), 0.10) is None
