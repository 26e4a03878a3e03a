"""Saving and loading trained socnav policies in a safe format (`socnav.rl.archive`: JSON and tensors only), and the
policies shipped in the package by name. A policy file (`save_policy`, `socnav.load_policy`) is a zip archive holding
    socnav.json  {"format": "socnav-policy", "version": 1, "algo": ..., "algo_config": {...}, "env_config": {...}, ...}
    policy.pt    the policy's ``state_dict`` (tensors only, read with ``torch.load(weights_only=True)``).
Training checkpoints are `socnav.rl.checkpoints` (re-exported here).
"""

from __future__ import annotations

import io
import json
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import torch as th
from pydantic import (
    Field,
    StrictInt,
    ValidationError,
)

from socnav.rl.archive import (
    MAX_HEADER_BYTES,
    MAX_TENSOR_BYTES,
    ArchiveHeader,
    check_scan_fov,
    check_state_dict,
    entry_is_finite,
    expected_shapes,
    load_tensors,
    parse_member_json,
    policy_for,
    read_members,
    validation_message,
    write_archive,
)
from socnav.rl.checkpoints import (
    CheckpointError,
    load_checkpoint,
    read_checkpoint_header,
    save_checkpoint,
    verify_checkpoint,
)
from socnav.rl.policy import ODVActorCriticPolicy

FORMAT_NAME = "socnav-policy"


FORMAT_VERSION = 1


METADATA_FILE = "socnav.json"


WEIGHTS_FILE = "policy.pt"


PRETRAINED = "pretrained"


PRETRAINED_MAPS = "pretrained-maps"


PRETRAINED_PPO = "pretrained-ppo"


#: name -> file in socnav/data of each shipped policy (socnav/data/README.md says how each was made and measured)
PRETRAINED_FILES = {PRETRAINED: "pretrained_odv_ppo_drop_position_swap.zip",
                    PRETRAINED_MAPS: "pretrained_odv_ppo_drop_maps.zip",
                    PRETRAINED_PPO: "pretrained_odv_ppo_drop_position_swap_ppo.zip"}


__all__ = [
    "CheckpointError", "PolicyLoadError", "entry_is_finite", "load_checkpoint", "load_policy", "pretrained_path",
    "read_checkpoint_header", "save_checkpoint", "save_policy", "training_world", "validation_message",
    "verify_checkpoint",
]


class PolicyLoadError(ValueError):
    """A file that is not a readable socnav policy (missing, corrupted, foreign or from an incompatible version)."""


def pretrained_path(name: str = PRETRAINED) -> Path:
    """Path of a policy shipped inside the package (socnav/data/README.md): ``"pretrained"``, ODV-PPO-Drop's network
    taught the open plane's position swap by imitation of the ORCA robot (DAgger; it drives smoothly),
    ``"pretrained-maps"``, the map policy (DAgger on the four map scenarios), or ``"pretrained-ppo"``, ODV-PPO-Drop
    trained by PPO on position swap as in the paper (it turns bang-bang; `pretrained` until DAgger
    replaced it)."""
    if name not in PRETRAINED_FILES:
        raise PolicyLoadError(f"no shipped policy named {name!r}; the shipped ones are {', '.join(PRETRAINED_FILES)}")
    return Path(str(resources.files("socnav") / "data" / PRETRAINED_FILES[name]))


class PolicyHeader(ArchiveHeader):
    """``socnav.json`` of a policy file."""

    format: Literal["socnav-policy"]
    version: Literal[1]
    timesteps: StrictInt | None = Field(None, ge=0)


def save_policy(policy: ODVActorCriticPolicy, path: str | Path, metadata: dict[str, Any]) -> Path:
    """Write `policy` and JSON-safe `metadata` (must hold ``algo``, ``algo_config``, ``env_config``) atomically."""
    for key in ("algo", "algo_config", "env_config"):
        if key not in metadata:
            raise ValueError(f"policy metadata needs {key!r}; got keys {sorted(metadata)}")
    check_scan_fov(policy, metadata["env_config"])
    header = {"format": FORMAT_NAME, "version": FORMAT_VERSION, **metadata}
    weights = io.BytesIO()
    th.save({name: tensor.detach().cpu() for name, tensor in policy.state_dict().items()}, weights)
    return write_archive(Path(path), {METADATA_FILE: json.dumps(header, indent=2, sort_keys=True).encode(),
                                       WEIGHTS_FILE: weights.getvalue()})


def _read_archive(path: Path) -> tuple[dict[str, Any], PolicyHeader, bytes]:
    members = read_members(path, {METADATA_FILE: MAX_HEADER_BYTES, WEIGHTS_FILE: MAX_TENSOR_BYTES},
                            PolicyLoadError, "policy", shipped=list(PRETRAINED_FILES))
    header = parse_member_json(members[METADATA_FILE], path, METADATA_FILE, PolicyLoadError)
    if not isinstance(header, dict) or header.get("format") != FORMAT_NAME:
        raise PolicyLoadError(f"{path}: {METADATA_FILE} does not declare format {FORMAT_NAME!r}")
    if header.get("version") != FORMAT_VERSION:
        raise PolicyLoadError(
            f"{path}: policy format version {header.get('version')!r} is not supported; allowed: {FORMAT_VERSION}"
        )
    try:
        return header, PolicyHeader.model_validate(header), members[WEIGHTS_FILE]
    except ValidationError as exc:
        raise PolicyLoadError(f"{path}: invalid policy metadata: {validation_message(exc)}") from None


def load_policy(path: str | Path) -> ODVActorCriticPolicy:
    """Load a policy written by `save_policy` / `socnav train`, or a shipped one by name: ``"pretrained"`` (the open
    plane), ``"pretrained-maps"`` (walls and the open plane) or ``"pretrained-ppo"`` (the open plane, trained by PPO
    as in the paper; socnav/data/README.md says how each was made).

    The returned SB3 policy is in eval mode (dropout off); ``policy.predict(obs, deterministic=True)`` gives the
    mean action. Its metadata is on ``policy.socnav_metadata`` (algo, algo_config, env_config, timesteps, ...).

    :raises PolicyLoadError: missing, corrupted, foreign, crafted or incompatible file (one line). Nothing is
        unpickled: the header is JSON and the weights are read with ``torch.load(weights_only=True)``.
    """
    from socnav.config import ConfigError, load_config

    path = pretrained_path(str(path)) if str(path) in PRETRAINED_FILES else Path(path)
    raw_header, header, weights = _read_archive(path)
    try:
        env_config = load_config(header.env_config)
    except ConfigError as exc:
        raise PolicyLoadError(f"{path}: invalid policy metadata: {' '.join(str(exc).split())}") from None
    state = load_tensors(weights, path, WEIGHTS_FILE, PolicyLoadError)
    check_state_dict(state, expected_shapes(header.algo_config, env_config), path, WEIGHTS_FILE, PolicyLoadError)
    policy = policy_for(header.algo_config, env_config)
    policy.load_state_dict(state, strict=True)  # names and shapes checked above
    policy.set_training_mode(False)
    policy.socnav_metadata = raw_header  # validated above
    return policy


def training_world(policy: Any, scenario: str | None = None, n_humans: int | None = None,
                   max_humans: int | None = None) -> tuple[dict[str, Any], str]:
    """The env config a loaded policy is evaluated in unless told otherwise: the world it was trained in (its
    ``socnav_metadata["env_config"]``), and where that world comes from in words.

    `scenario`, `n_humans` and `max_humans` are the overrides the caller applies on top (``load_config(world,
    **overrides)``); they are not applied here. A scenario other than the training one drops the stored
    ``n_humans``, so that the new scenario starts from its own number of humans.

    :returns: (the env config as a JSON dict, to build with ``load_config``; "the model's training world", with
        ", changed by the options" when any override is given).
    """
    world = dict(policy.socnav_metadata["env_config"])  # a copy: the policy's metadata stays as loaded
    if scenario is not None and scenario != world.get("scenario"):
        world["n_humans"] = None
    changed = scenario is not None or n_humans is not None or max_humans is not None
    return world, "the model's training world" + (", changed by the options" if changed else "")

