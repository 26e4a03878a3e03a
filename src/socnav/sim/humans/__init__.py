"""Models of how the humans walk, behind one plug point: the `HumanModel` protocol and a registry of models by name.

The config field ``humans.model`` picks one (``orca``, the default, or ``social_force``); `register_human_model`
adds your own. Every model gets the same inputs, including attention and personal space (see `Crowd`).
"""

from __future__ import annotations

from typing import Callable

from socnav.sim.humans.base import Crowd, HumanModel, HumanSettings
from socnav.sim.humans.orca import OrcaHumans
from socnav.sim.humans.social_force import SocialForceHumans

__all__ = [
    "Crowd", "HumanModel", "HumanModelFactory", "HumanSettings", "OrcaHumans", "SocialForceHumans",
    "human_model_names", "make_human_model", "register_human_model",
]

#: Builds a model from a world's config (`socnav.config.EnvConfig`, read through `HumanSettings`).
HumanModelFactory = Callable[[HumanSettings], HumanModel]

_REGISTRY: dict[str, HumanModelFactory] = {}


def register_human_model(name: str, factory: HumanModelFactory) -> HumanModelFactory:
    """Register `factory` under `name` (replacing one of the same name); ``humans.model: name`` then selects it."""
    _REGISTRY[name] = factory
    return factory


def human_model_names() -> list[str]:
    """The registered model names, in registration order (the default, ``orca``, first)."""
    return list(_REGISTRY)


def make_human_model(config: HumanSettings) -> HumanModel:
    """The model ``config.humans.model`` names, built from `config` (KeyError listing the registered names)."""
    name = config.humans.model
    try:
        factory = _REGISTRY[name]
    except KeyError:
        raise KeyError(f"unknown human model {name!r}; registered: {', '.join(human_model_names())}") from None
    return factory(config)


register_human_model(OrcaHumans.name, OrcaHumans.from_config)
register_human_model(SocialForceHumans.name, SocialForceHumans.from_config)
