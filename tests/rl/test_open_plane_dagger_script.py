"""docs/analysis/open_plane_dagger.py, the smooth open-plane candidate of docs/training.md: a tiny clone and one
DAgger round, its feature range set over the states it drives into (an imitation-trained policy has none)."""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

import numpy as np
import pytest

import socnav

SCRIPT = Path(__file__).resolve().parents[2] / "docs" / "analysis" / "open_plane_dagger.py"


def _run(monkeypatch, capsys, *args: str) -> str:
    monkeypatch.setattr(sys, "argv", [str(SCRIPT), *args])
    runpy.run_path(str(SCRIPT), run_name="__main__")
    return capsys.readouterr().out


def test_a_tiny_dagger_run_saves_a_policy_with_its_feature_range(tmp_path, monkeypatch, capsys):
    printed = _run(monkeypatch, capsys, "--steps", "1500", "--rounds", "1", "--feature-range", "160",
                   "--out", str(tmp_path / "ranged.zip"))
    assert "round 0:" in printed and "round 1:" in printed
    ranged = socnav.load_policy(tmp_path / "ranged.zip")
    assert ranged.socnav_metadata["env_config"]["scenario"] == "position_swap"
    h_min, h_max = (bound.numpy() for bound in ranged.feature_range)
    assert np.isfinite(h_min).all() and np.isfinite(h_max).all() and (h_max > h_min).any()
    _run(monkeypatch, capsys, "--steps", "1500", "--rounds", "1", "--feature-range", "0",
         "--out", str(tmp_path / "unranged.zip"))
    unranged = socnav.load_policy(tmp_path / "unranged.zip")
    assert not np.isfinite(unranged.feature_range[0].numpy()).any()
    for name, tensor in unranged.state_dict().items():  # the same run otherwise: the same weights
        if not name.endswith(("h_min", "h_max")):
            np.testing.assert_array_equal(tensor.numpy(), ranged.state_dict()[name].numpy(), err_msg=name)


def test_worlds_share_the_labels_and_the_first_names_the_policy(tmp_path, monkeypatch, capsys):
    printed = _run(monkeypatch, capsys, "--steps", "3200", "--rounds", "0", "--feature-range", "0",
                   "--worlds", "circle_crossing:3", "position_swap:1", "--out", str(tmp_path / "mixed.zip"))
    labels = int(printed.split("round 0: ")[1].split(" labels")[0].replace(",", ""))
    # 1,600 steps per world from 16 environments: each world's collection ends with its last finished episode
    assert 0 < labels <= 3200
    world = socnav.load_policy(tmp_path / "mixed.zip").socnav_metadata["env_config"]
    assert (world["scenario"], world["n_humans"]) == ("circle_crossing", 3)
    script = runpy.run_path(str(SCRIPT))
    assert script["parse_world"]("random") == {"scenario": "random"}
    assert script["parse_world"]("position_swap:1") == {"scenario": "position_swap", "n_humans": 1}
    with pytest.raises(ValueError, match=r"whole number, got 'x'"):
        script["parse_world"]("position_swap:x")
    with pytest.raises(ValueError, match=r"unknown scenario 'bogus'; allowed: circle_crossing"):
        script["parse_world"]("bogus")
