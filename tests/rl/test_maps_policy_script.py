"""docs/analysis/maps_policy.py, the script behind docs/maps.md's tables of learned map policies: a tiny supervised
start with one DAgger round, then PPO continued from it under another collision penalty, end to end."""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

import numpy as np
import pytest

import socnav

SCRIPT = Path(__file__).resolve().parents[2] / "docs" / "analysis" / "maps_policy.py"


def _run(monkeypatch, *args: str) -> None:
    monkeypatch.setattr(sys, "argv", [str(SCRIPT), *args])
    runpy.run_path(str(SCRIPT), run_name="__main__")


def test_clone_dagger_then_continue(tmp_path, monkeypatch, capsys):
    out = tmp_path / "cloned.zip"
    _run(monkeypatch, "--clone", "3000", "--dagger", "1", "--clone-epochs", "1", "--dagger-epochs", "1",
         "--frame", "heading", "--scan-people", "--scan-encoding", "nearness", "--teacher-turn", "goal",
         "--steps", "0", "--out", str(out))
    printed = capsys.readouterr().out
    assert "round 0:" in printed and "round 1:" in printed and "driven_" in printed
    clone = socnav.load_policy(tmp_path / "cloned_clone.zip")
    assert clone.features_extractor.frame == "heading"
    assert clone.features_extractor.scan_encoder.encoding == "nearness"
    assert clone.socnav_metadata["env_config"]["scan"]["people"] is True
    _run(monkeypatch, "--start", str(tmp_path / "cloned_clone.zip"), "--collision-penalty", "50", "--steps", "2048",
         "--chunk", "2048", "--out", str(tmp_path / "continued.zip"))
    continued = socnav.load_policy(tmp_path / "continued.zip")
    assert continued.socnav_metadata["timesteps"] == 2048
    assert continued.socnav_metadata["env_config"]["reward"]["collision"] == pytest.approx(50.0)
    assert continued.socnav_metadata["env_config"]["scan"]["people"] is True  # the start's world, kept
    assert continued.features_extractor.scan_encoder.encoding == "nearness"
    # imitation leaves the feature range untracked; --feature-range sets it over the states the policy drives into
    assert not np.isfinite(clone.feature_range[0].numpy()).any()
    _run(monkeypatch, "--start", str(tmp_path / "cloned_clone.zip"), "--steps", "0", "--feature-range", "64",
         "--out", str(tmp_path / "ranged.zip"))
    ranged = socnav.load_policy(tmp_path / "ranged.zip")
    h_min, h_max = (bound.numpy() for bound in ranged.feature_range)
    assert np.isfinite(h_min).all() and np.isfinite(h_max).all() and (h_max > h_min).any()
    for name, tensor in clone.state_dict().items():  # the weights are the clone's
        if not name.endswith(("h_min", "h_max")):
            np.testing.assert_array_equal(tensor.numpy(), ranged.state_dict()[name].numpy(), err_msg=name)


def test_dagger_rounds_are_saved_and_a_later_run_continues_after_the_last(tmp_path, monkeypatch, capsys):
    """``--rounds-dir``: the policy after each round is saved; a run with more rounds re-collects the saved rounds'
    labels with the policies that drove them (the same labelled steps) and fits only the new round."""
    rounds = tmp_path / "rounds"
    common = ["--clone", "2000", "--clone-epochs", "1", "--dagger-epochs", "1", "--steps", "0",
              "--rounds-dir", str(rounds)]
    _run(monkeypatch, *common, "--dagger", "1", "--out", str(tmp_path / "first.zip"))
    first = capsys.readouterr().out
    assert sorted(path.name for path in rounds.iterdir()) == ["round_000.zip", "round_001.zip"]
    _run(monkeypatch, *common, "--dagger", "2", "--out", str(tmp_path / "second.zip"))
    second = capsys.readouterr().out
    assert "continuing after round 1" in second and (rounds / "round_002.zip").exists()
    assert second.count("clone epoch") == 1  # rounds 0 and 1 were not fitted again
    for round_ in (0, 1):  # the same labelled steps, episode ends and all
        line = next(line for line in first.splitlines() if line.startswith(f"round {round_}:"))
        again = next(line for line in second.splitlines() if line.startswith(f"round {round_}:"))
        assert line.rsplit(",", 1)[0] == again.rsplit(",", 1)[0]
    np.testing.assert_allclose(
        [p.detach().numpy().sum() for p in socnav.load_policy(tmp_path / "second_clone.zip").parameters()],
        [p.detach().numpy().sum() for p in socnav.load_policy(rounds / "round_002.zip").parameters()])


def test_dagger_from_a_start_with_the_safety_layer_driving(tmp_path, monkeypatch, capsys):
    """``--start`` with ``--clone`` continues imitation from a saved policy; ``--driver-safety`` makes the DAgger
    rounds' driver the policy inside the safety layer, so other states are labelled than with the policy alone;
    ``--evaluate ... --safety`` adds each policy, the ORCA robot and `straight` inside the layer with the share of
    steps its fallback drove."""
    trigger = Path(socnav.__file__).parent / "data" / "pretrained-ppo_time-to-collision.yaml"
    _run(monkeypatch, "--clone", "2000", "--clone-epochs", "1", "--steps", "0", "--out", str(tmp_path / "a.zip"))
    capsys.readouterr()
    common = ["--start", str(tmp_path / "a_clone.zip"), "--clone", "1500", "--clone-epochs", "1", "--dagger", "1",
              "--dagger-epochs", "1", "--steps", "0"]
    _run(monkeypatch, *common, "--out", str(tmp_path / "plain.zip"))
    plain = capsys.readouterr().out
    _run(monkeypatch, *common, "--driver-safety", str(trigger), "--out", str(tmp_path / "safe.zip"))
    safe = capsys.readouterr().out

    def round_line(printed: str, round_: int) -> str:
        return next(line for line in printed.splitlines() if line.startswith(f"round {round_}:")).rsplit(",", 1)[0]

    assert round_line(plain, 0) == round_line(safe, 0)  # the teacher drives round 0 in both
    assert round_line(plain, 1) != round_line(safe, 1)  # the layer drove round 1 elsewhere
    started = socnav.load_policy(tmp_path / "safe_clone.zip")
    assert started.socnav_metadata["env_config"]["scenario"] == "doorway"
    _run(monkeypatch, "--evaluate", f"safe={tmp_path / 'safe_clone.zip'}", "--safety", str(trigger),
         "--episodes", "2")
    table = capsys.readouterr().out
    for driver in ("safe", "ORCA robot", "straight"):  # four map scenarios and two open-plane ones each
        assert table.count(f"| {driver} + safety (fallback ") == 6
    # the docs' form: a row per controller, a goal / people / walls cell per scenario, as the long table's rates
    summary = table[table.index("\n| controller | corridor | doorway | intersection | room | position swap | "
                                "circle crossing |"):]
    long_rows = [line for line in table.splitlines() if line.startswith("| corridor | safe + safety")]
    goal = float(long_rows[0].split("|")[3].split()[0])
    safe_row = next(line for line in summary.splitlines() if line.startswith("| safe + safety |"))
    cells = [cell.strip() for cell in safe_row.split("|")[2:-1]]
    assert len(cells) == 6 and cells[0].startswith(f"{goal:g} / ") and cells[0].endswith(" %)")
    _run(monkeypatch, "--evaluate", f"safe={tmp_path / 'safe_clone.zip'}", "--episodes", "1", "--scenarios", "room")
    lines = capsys.readouterr().out.splitlines()
    scenarios = {line.split("|")[1].strip() for line in lines if line.startswith("| ") and "controller" not in line}
    assert scenarios == {"room", "ORCA robot", "safe"}  # the long table's rows, then the docs' table's
    assert "| controller | room |" in lines
