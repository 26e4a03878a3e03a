"""Saving and loading trained socnav policies in a safe format: no pickled objects, only JSON and tensors.
`socnav.load_policy(path)` rebuilds the network from its recorded config and loads weights with `weights_only=True`.

A policy file is a zip archive holding
    socnav.json  {"format": "socnav-policy", "version": 1, "algo": ..., "algo_config": {...}, "env_config": {...}, ...}
    policy.pt    the policy's ``state_dict`` (tensors only, read with ``torch.load(weights_only=True)``).
SB3's own ``model.save`` format pickles objects (``cloudpickle``), so loading one from an untrusted source can run
arbitrary code; we keep it only for our own resumable training checkpoints and never for ``load_policy``.
"""

from __future__ import annotations

import io
import json
import zipfile
from importlib import resources
from pathlib import Path
from typing import Any

import torch as th

from socnav.rl.policy import ODVActorCriticPolicy
from socnav.rl.presets import AlgoConfig, policy_kwargs_for

FORMAT_NAME = "socnav-policy"
FORMAT_VERSION = 1
METADATA_FILE = "socnav.json"
WEIGHTS_FILE = "policy.pt"
PRETRAINED = "pretrained"

__all__ = ["PolicyLoadError", "load_policy", "pretrained_path", "save_policy"]


class PolicyLoadError(ValueError):
    """A file that is not a readable socnav policy (missing, corrupted, foreign or from an incompatible version)."""


def pretrained_path() -> Path:
    """Path of the ODV-PPO-Drop position-swap policy shipped inside the package (see socnav/data/README.md)."""
    return Path(str(resources.files("socnav") / "data" / "pretrained_odv_ppo_drop_position_swap.zip"))


def save_policy(policy: ODVActorCriticPolicy, path: str | Path, metadata: dict[str, Any]) -> Path:
    """Write `policy` and JSON-safe `metadata` (must hold ``algo``, ``algo_config``, ``env_config``) atomically."""
    from socnav.io import atomic_path

    for key in ("algo", "algo_config", "env_config"):
        if key not in metadata:
            raise ValueError(f"policy metadata needs {key!r}; got keys {sorted(metadata)}")
    header = {"format": FORMAT_NAME, "version": FORMAT_VERSION, **metadata}
    weights = io.BytesIO()
    th.save({name: tensor.detach().cpu() for name, tensor in policy.state_dict().items()}, weights)
    path = Path(path)
    with atomic_path(path) as temporary:
        with zipfile.ZipFile(temporary, "w", compression=zipfile.ZIP_DEFLATED) as archive:
            archive.writestr(METADATA_FILE, json.dumps(header, indent=2, sort_keys=True))
            archive.writestr(WEIGHTS_FILE, weights.getvalue())
    return path


def _read_archive(path: Path) -> tuple[dict[str, Any], bytes]:
    if not path.is_file():
        raise PolicyLoadError(f"no policy file at {path}")
    try:
        with zipfile.ZipFile(path) as archive:
            names = set(archive.namelist())
            if METADATA_FILE not in names or WEIGHTS_FILE not in names:
                hint = " (an SB3 model zip? socnav policies are written by `socnav train`)" if "data" in names else ""
                raise PolicyLoadError(
                    f"{path} is not a socnav policy: it lacks {METADATA_FILE} and {WEIGHTS_FILE}{hint}"
                )
            header = json.loads(archive.read(METADATA_FILE))
            weights = archive.read(WEIGHTS_FILE)
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, OSError) as exc:
        raise PolicyLoadError(f"{path} is not a readable socnav policy (corrupted or not a zip archive: {exc})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise PolicyLoadError(f"{path}: {METADATA_FILE} is not valid JSON ({exc})") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT_NAME:
        raise PolicyLoadError(f"{path}: {METADATA_FILE} does not declare format {FORMAT_NAME!r}")
    if header.get("version") != FORMAT_VERSION:
        raise PolicyLoadError(
            f"{path}: policy format version {header.get('version')!r} is not supported; allowed: {FORMAT_VERSION}"
        )
    return header, weights


def load_policy(path: str | Path) -> ODVActorCriticPolicy:
    """Load a policy written by `save_policy` / `socnav train`, or ``"pretrained"`` for the shipped one.

    The returned SB3 policy is in eval mode (dropout off); ``policy.predict(obs, deterministic=True)`` gives the
    mean action. Its metadata is on ``policy.socnav_metadata`` (algo, algo_config, env_config, timesteps, ...).

    :raises PolicyLoadError: missing, corrupted, foreign or incompatible file. Nothing is unpickled: the header is
        JSON and the weights are read with ``torch.load(weights_only=True)``.
    """
    from socnav.config import ConfigError, load_config
    from socnav.envs.spaces import action_space, observation_space

    path = pretrained_path() if str(path) == PRETRAINED else Path(path)
    header, weights = _read_archive(path)
    try:
        algo_config = AlgoConfig.model_validate(header["algo_config"])
        env_config = load_config(header["env_config"])
    except (KeyError, ValueError, ConfigError) as exc:
        raise PolicyLoadError(f"{path}: invalid policy metadata ({exc})") from None
    try:
        state = th.load(io.BytesIO(weights), map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for corrupted / non-tensor payloads
        raise PolicyLoadError(f"{path}: {WEIGHTS_FILE} is not a tensors-only state dict ({type(exc).__name__}: {exc})") from None
    policy = ODVActorCriticPolicy(
        observation_space(env_config.max_humans), action_space(), lambda _: 0.0, **policy_kwargs_for(algo_config)
    )
    if not isinstance(state, dict):
        raise PolicyLoadError(f"{path}: {WEIGHTS_FILE} does not hold a state dict")
    try:
        policy.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise PolicyLoadError(f"{path}: weights do not fit the recorded network ({exc})") from None
    policy.set_training_mode(False)
    policy.socnav_metadata = header  # type: ignore[attr-defined]
    return policy
