"""Assembly of the safety layer from its parts: the policy that acts, an uncertainty estimator over it (MC dropout
or a deep ensemble, paper section IV-B) and the thresholds of the collision rule (paper section IV-C).

`socnav evaluate --safety` builds its layer with :func:`assemble_safe_policy`; `socnav animate` and `socnav calibrate`
take the estimator alone from :func:`make_safety_estimator`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

from socnav.safety.rule import Thresholds
from socnav.safety.safe_policy import SafePolicy
from socnav.safety.triggers import TriggerSpec, load_safety

if TYPE_CHECKING:
    from socnav.config import ConfigLike
    from socnav.uncertainty import EnsembleEstimator, MCDropoutEstimator

__all__ = [
    "SafetyAssemblyError",
    "assemble_safe_policy",
    "default_estimator_kind",
    "has_mc_dropout",
    "make_safety_estimator",
]


class SafetyAssemblyError(ValueError):
    """The parts given cannot make a safety layer: an unknown estimator kind, MC dropout over a policy trained
    without dropout, or an ensemble of fewer than two members."""


def default_estimator_kind(thresholds: str) -> str:
    """The estimator that thresholds given by name read: ``ensemble`` for the ensemble preset, else ``mc`` (the mc
    preset, and a `socnav calibrate` file, whose estimator the command line names with --estimator)."""
    return "ensemble" if thresholds == "ensemble" else "mc"


def has_mc_dropout(policy: Any) -> bool:
    """Whether MC dropout has something to sample in `policy`: it has dropout layers and was trained with dropout
    (``p_train > 0``: the ``algo_config`` recorded in its policy file, else its ``dropout_p``). A network trained
    without dropout gives K identical samples: no uncertainty."""
    metadata = getattr(policy, "socnav_metadata", None)
    if metadata is not None:
        trained_with = float(metadata.get("algo_config", {}).get("p_train", 0.0))
    else:
        trained_with = float(policy.dropout_p)
    return bool(policy.dropout_layers()) and trained_with != 0.0


def make_safety_estimator(kind: str, policy: Any, members: Sequence[Any] = (),
                          k: int = 20) -> MCDropoutEstimator | EnsembleEstimator:
    """The uncertainty estimator the safety layer reads.

    :param kind: ``mc``: K MC-dropout samples of `policy`, from a private mask stream seeded with
        `socnav.uncertainty.MC_SEED` (the same decisions at every run); ``ensemble``: the deep ensemble of `members`.
    :param policy: the policy that acts (sampled by ``mc``).
    :param members: the ensemble's policies (``ensemble`` only), at least two.
    :param k: MC-dropout samples K (``mc`` only).
    :raises SafetyAssemblyError: an unknown `kind`, ``mc`` over a policy without MC dropout (:func:`has_mc_dropout`),
        ``ensemble`` with fewer than two members.
    """
    from socnav.uncertainty import ESTIMATOR_KINDS, MC_SEED, MCDropoutEstimator, make_estimator

    if kind not in ESTIMATOR_KINDS:
        raise SafetyAssemblyError(f"estimator {kind!r} is not known; allowed: {', '.join(ESTIMATOR_KINDS)}")
    if kind == "mc":
        if not has_mc_dropout(policy):
            raise SafetyAssemblyError("estimator 'mc' needs a policy trained with dropout (odv-ppo-drop, ppo-drop): "
                                      "its MC-dropout samples would all be the same; use an ensemble")
        return MCDropoutEstimator(policy, k=k, seed=MC_SEED)
    if len(members) < 2:
        raise SafetyAssemblyError(f"an ensemble needs at least 2 members, got {len(members)}")
    return make_estimator("ensemble", list(members))


def assemble_safe_policy(policy: Any, thresholds: Thresholds | TriggerSpec | str | Mapping[str, Any],
                         env_config: ConfigLike,
                         estimator: str = "mc", members: Sequence[Any] = (), k: int = 20) -> SafePolicy:
    """`policy` wrapped in the safety layer: the collision rule with `thresholds` reads the uncertainty of the
    `estimator` (:func:`make_safety_estimator`), and the cautious controller acts where the rule fires.

    :param policy: the policy that acts (e.g. `socnav.rl.persistence.load_policy`'s); with ``ensemble``, often the
        first member.
    :param thresholds: `Thresholds`, a preset name (``mc``, ``ensemble``), a `socnav calibrate` file or a mapping,
        or a trigger (`socnav.safety.triggers.TriggerSpec`, or its file); a trigger that reads no uncertainty
        gets no estimator.
    :param env_config: the world the layer acts in (its cautious controller's radii and speeds).
    :param estimator: ``mc`` or ``ensemble``.
    :param members: the ensemble's policies (``ensemble`` only).
    :param k: MC-dropout samples K (``mc`` only).
    :raises SafetyAssemblyError: as :func:`make_safety_estimator`.
    :raises socnav.safety.ThresholdsError: invalid `thresholds`.
    """
    decision = load_safety(thresholds)
    # a trigger that reads no uncertainty (proximity-only, time to collision, ...) gets no estimator: its cost is
    # K forward passes per step for MC dropout
    uncertainty = make_safety_estimator(estimator, policy, members, k) if decision.uses_uncertainty else None
    return SafePolicy(policy, uncertainty, decision, env_config)
