"""The Gymnasium-style docstring of `SocialNavEnv` stays true to the code: feature tables, reward weights, outcomes."""

from __future__ import annotations

import re

import pytest

from socnav.config import RewardConfig
from socnav.envs.env import SocialNavEnv
from socnav.envs.spaces import ACTION_NAMES, HUMAN_FEATURE_NAMES, ROBOT_FEATURE_NAMES
from socnav.sim import world
from socnav.sim.world import HUMAN_FEATURES, OUTCOME_NAMES, ROBOT_FEATURES


def sections() -> dict[str, str]:
    """The docstring's `## Heading` sections by heading."""
    parts = re.split(r"^\s*## (.+)$", SocialNavEnv.__doc__, flags=re.MULTILINE)
    return {title.strip(): body for title, body in zip(parts[1::2], parts[2::2], strict=True)}


def tables(text: str) -> list[list[list[str]]]:
    """The Markdown tables of `text`: a list of row lists (header and separator rows dropped), cells stripped."""
    found, rows = [], []
    for line in [*text.splitlines(), ""]:
        line = line.strip()
        if line.startswith("|"):
            rows.append([cell.strip() for cell in line.strip("|").split("|")])
        elif rows:
            found.append(rows[2:])  # header, separator
            rows = []
    return found


def test_the_docstring_has_the_gymnasium_sections():
    assert list(sections()) == ["Description", "Action Space", "Observation Space", "Rewards", "Starting State",
                                "Episode End", "Arguments", "Version History"]


def test_observation_tables_list_exactly_the_feature_names_in_order():
    robot, humans = tables(sections()["Observation Space"])
    for rows, names, count in ((robot, ROBOT_FEATURE_NAMES, ROBOT_FEATURES),
                               (humans, HUMAN_FEATURE_NAMES, HUMAN_FEATURES)):
        assert [row[0] for row in rows] == [str(k) for k in range(len(rows))]
        assert tuple(row[1].strip("`") for row in rows) == names
        assert len(names) == count  # the kernel's array widths
    text = sections()["Observation Space"]
    assert f"`robot`, `Box(-inf, inf, ({ROBOT_FEATURES},))`" in text
    assert f"`humans`, `Box(-inf, inf, (max_humans, {HUMAN_FEATURES}))`" in text


def test_action_table_lists_the_action_names_in_order():
    (rows,) = tables(sections()["Action Space"])
    assert [row[0] for row in rows] == ["0", "1"]
    assert tuple(row[1].strip("`") for row in rows) == ACTION_NAMES


def test_reward_table_names_every_weight_with_its_default():
    (rows,) = tables(sections()["Rewards"])
    documented = {row[1].strip("`").removeprefix("reward."): float(row[2]) for row in rows}
    assert documented == RewardConfig().model_dump()


@pytest.mark.parametrize("code", sorted(OUTCOME_NAMES))
def test_episode_end_names_every_outcome_with_its_constant(code):
    name = OUTCOME_NAMES[code]
    constant = f"OUTCOME_{name.upper()}"
    assert getattr(world, constant) == code
    assert f'`"{name}"` (`{constant}`)' in sections()["Episode End"]
