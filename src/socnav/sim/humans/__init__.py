"""Models of how the humans walk, behind one plug point: the `HumanModel` protocol and a registry of models by name.

The config field ``humans.model`` picks one (``orca``, the default, ``social_force`` or ``replay``: recorded
trajectories, with the ``replay`` scenario); ``humans.mix`` mixes several per human (`MixedHumans`, ``model: mix``);
`register_human_model` adds your own. Every model gets the same inputs, including attention and personal space
(see `Crowd`).
"""

from __future__ import annotations

from collections.abc import Callable

from socnav.sim.humans.base import Crowd, HumanModel, HumanSettings, ScriptedHumans
from socnav.sim.humans.mix import MIX, MixedHumans
from socnav.sim.humans.orca import OrcaHumans
from socnav.sim.humans.replay import ReplayHumans, TrajectoryFileError
from socnav.sim.humans.social_force import SocialForceHumans

__all__ = [
    "HUMAN_MODELS", "MIX", "Crowd", "HumanModel", "HumanModelFactory", "HumanSettings", "MixedHumans", "OrcaHumans",
    "ReplayHumans", "ScriptedHumans", "SocialForceHumans", "TrajectoryFileError", "human_model_names",
    "make_human_model", "register_human_model",
]

#: Builds a model from a world's config (`socnav.config.EnvConfig`, read through `HumanSettings`).
HumanModelFactory = Callable[[HumanSettings], HumanModel]

#: The registered models, by name, in registration order; `register_human_model` adds to it.
HUMAN_MODELS: dict[str, HumanModelFactory] = {}


def register_human_model(name: str, factory: HumanModelFactory) -> HumanModelFactory:
    """Register `factory` under `name` (replacing one of the same name); ``humans.model: name`` then selects it."""
    HUMAN_MODELS[name] = factory
    return factory


def human_model_names() -> list[str]:
    """The registered model names, in registration order (the default, ``orca``, first)."""
    return list(HUMAN_MODELS)


def make_human_model(config: HumanSettings) -> HumanModel:
    """The model ``config.humans.model`` names -- or ``config.perturbation.human_model`` when set (the behaviour
    shift perturbation) -- built from `config` (KeyError listing the registered names)."""
    shifted = getattr(getattr(config, "perturbation", None), "human_model", None)
    name = shifted if shifted is not None else config.humans.model
    if name == MIX:  # a mixed crowd (humans.mix): every model of the mix, built the same way
        return MixedHumans.from_shares(config.humans.mix, lambda model: _build(model, config))
    return _build(name, config)


def _build(name: str, config: HumanSettings) -> HumanModel:
    try:
        factory = HUMAN_MODELS[name]
    except KeyError:
        raise KeyError(f"unknown human model {name!r}; registered: {', '.join(human_model_names())}") from None
    return factory(config)


register_human_model(OrcaHumans.name, OrcaHumans.from_config)
register_human_model(SocialForceHumans.name, SocialForceHumans.from_config)
register_human_model(ReplayHumans.name, ReplayHumans.from_config)
