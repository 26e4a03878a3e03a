"""The options several `socnav` commands take, declared once: each function returns the `typer.Option` of one flag
(its name, bounds and help), and every command that takes the flag declares it with that function.

Typer's default-value style, as the commands use: a command passes its own default, and its own ``help`` where the
option means something more there (e.g. what its default is in that command). The bounds of episode and timestep
counts are the experiment files' (`socnav.experiments.spec`), so a flag and its YAML field refuse the same values.
"""

from __future__ import annotations

from types import EllipsisType
from typing import Any

import typer

from socnav.experiments.spec import MAX_EPISODES, MAX_TIMESTEPS
from socnav.sim.scenarios import scenario_names

__all__ = [
    "ACTING_MODEL_HELP",
    "LAYER_SENSING_HELP",
    "MAX_MC_SAMPLES",
    "SCENARIOS",
    "SINGLE_AGENT_MAX_HUMANS_HELP",
    "SINGLE_AGENT_N_HUMANS_HELP",
    "SINGLE_AGENT_SCENARIO_HELP",
    "algo_option",
    "config_option",
    "episodes_option",
    "estimator_option",
    "eval_episodes_option",
    "eval_every_option",
    "force_option",
    "humans_option",
    "max_humans_option",
    "mc_samples_option",
    "members_option",
    "model_option",
    "n_envs_option",
    "n_humans_option",
    "perturb_option",
    "safety_option",
    "scenario_option",
    "seed_option",
    "sensing_option",
    "timesteps_option",
]

#: The most MC-dropout samples per decision a command takes (--k): the exported navigator's bound,
#: `socnav.runtime.format.MAX_K` (tested equal). Not imported from there: `socnav.runtime` loads onnxruntime, an
#: optional extra, and `socnav --help` must stay fast. 1,000 samples of the shipped policy in a batch of 32
#: environments already take about 4 MB a step; a million took 3.9 GB.
MAX_MC_SAMPLES = 1000

#: The scenario names, as the help of --scenario lists them.
SCENARIOS = ", ".join(scenario_names())

# Help texts that two commands share and that differ from the option's usual one. `animate` and `calibrate` play a
# single-agent world (position swap with one human unless given) with a model that acts and is estimated on.
SINGLE_AGENT_SCENARIO_HELP = f"one of: {SCENARIOS} (default: position_swap, or the --config file's)"
SINGLE_AGENT_N_HUMANS_HELP = "humans per episode (default: 1, or the --config file's)"
SINGLE_AGENT_MAX_HUMANS_HELP = "observation rows (default 10; the model's value)"
ACTING_MODEL_HELP = ("policy file, 'pretrained', 'pretrained-maps' or 'pretrained-ppo' (acts; MC-dropout estimates "
                     "on it)")
#: --sensing of the commands that wrap a policy in the safety layer (`calibrate` chooses it for its thresholds).
LAYER_SENSING_HELP = ("what the safety layer's proximity terms and fallback read: perceived (the noisy observation) | "
                      "true (the simulator's state); default: the thresholds' own (perceived for mc, ensemble)")


# ---- the world ---------------------------------------------------------------------------------------------------
def config_option() -> Any:
    """--config: a YAML env config, below the command's own world options."""
    return typer.Option(None, "--config", help="YAML env config; options above override it")


def scenario_option(default: str | EllipsisType | None, help: str) -> Any:
    """--scenario: the scenario to play (``...``: required; its help names the choices, `SCENARIOS`, and the
    command's default)."""
    return typer.Option(default, help=help)


def n_humans_option(help: str = "humans per episode (default: the scenario's)") -> Any:
    """--n-humans: humans per episode, >= 0 (None: the scenario's or config file's)."""
    return typer.Option(None, min=0, help=help)


def max_humans_option(help: str) -> Any:
    """--max-humans: observation rows, >= 1 (None: the config's default, 10)."""
    return typer.Option(None, min=1, help=help)


def humans_option() -> Any:
    """--humans: how the humans walk, the env config's ``humans.model`` (a `socnav.sim.humans` registry name; None:
    the world's own). Checked by the command, with did-you-mean, before any model loads."""
    return typer.Option(None, "--humans", metavar="MODEL",
                        help="human model (humans.model): orca | social_force | a registered one "
                             "(default: the world's)")


def perturb_option() -> Any:
    """--perturb key=value (repeatable): perturbation fields on top of the world's."""
    return typer.Option([], "--perturb", help="perturbation key=value (repeatable), e.g. heading_noise=0.8")


# ---- runs --------------------------------------------------------------------------------------------------------
def algo_option(default: str | EllipsisType) -> Any:
    """--algo: the training preset (``...``: required)."""
    return typer.Option(default, help="ppo | ppo-drop | odv-ppo-noloss | odv-ppo | odv-ppo-drop")


def seed_option(help: str, least: int | None = 0, most: int | None = None) -> Any:
    """--seed (default 0) in [least, most] (None: unbounded on that side)."""
    return typer.Option(0, min=least, max=most, help=help)


def episodes_option(default: int, help: str) -> Any:
    """--episodes: episodes a command plays, in [1, MAX_EPISODES]."""
    return typer.Option(default, min=1, max=MAX_EPISODES, help=help)


def eval_episodes_option(default: int) -> Any:
    """--eval-episodes: validation episodes of a training run, in [1, MAX_EPISODES]."""
    return typer.Option(default, min=1, max=MAX_EPISODES, help="validation episodes per evaluation")


def timesteps_option(default: int, help: str) -> Any:
    """--timesteps: environment steps of a training run, in [1, MAX_TIMESTEPS]."""
    return typer.Option(default, min=1, max=MAX_TIMESTEPS, help=help)


def eval_every_option(help: str) -> Any:
    """--eval-every: timesteps between validations, in [1, MAX_TIMESTEPS] (None: the command's schedule)."""
    return typer.Option(None, min=1, max=MAX_TIMESTEPS, help=help)


def n_envs_option(default: int, help: str = "environments stepped together") -> Any:
    """--n-envs: environments stepped together, >= 1."""
    return typer.Option(default, min=1, help=help)


# ---- outputs -----------------------------------------------------------------------------------------------------
def force_option(what: str = "the output file") -> Any:
    """--force: replace an existing output (without it a command refuses to overwrite one)."""
    return typer.Option(False, "--force", help=f"replace {what} if it exists")


# ---- policies, uncertainty and the safety layer -----------------------------------------------------------------
def model_option(help: str) -> Any:
    """--model: a trained policy file or a shipped one's name (None: the command runs without one)."""
    return typer.Option(None, help=help)


def estimator_option(default: str | None, help: str = "mc | ensemble") -> Any:
    """--estimator: the uncertainty estimator, mc (MC dropout) or ensemble."""
    return typer.Option(default, help=help)


def members_option() -> Any:
    """--members: the glob of an ensemble's policy files."""
    return typer.Option(None, help="ensemble policy files (glob), for --estimator ensemble")


def mc_samples_option(help: str = "MC-dropout samples") -> Any:
    """--k: MC-dropout samples per decision (default 20), in [2, MAX_MC_SAMPLES] as `socnav export --k`."""
    return typer.Option(20, min=2, max=MAX_MC_SAMPLES, help=help)


def safety_option(help: str) -> Any:
    """--safety: the thresholds of the safety layer, mc | ensemble | FILE (None: no safety layer)."""
    return typer.Option(None, help=help)


def sensing_option(default: str | None = None, help: str = LAYER_SENSING_HELP) -> Any:
    """--sensing: what the safety layer's proximity terms and fallback read, perceived or true."""
    return typer.Option(default, help=help)
