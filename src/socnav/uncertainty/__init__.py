"""Uncertainty estimation for socnav policies: MC-dropout and deep ensembles (paper IV-B; docs/uncertainty-safety.md).
Epistemic / aleatoric uncertainty per action dimension, predictive feature uncertainty, and their windowed mean.

Example::

    from socnav.uncertainty import make_estimator, WindowedUncertainty

    estimator = make_estimator("mc", policy, k=20)          # or make_estimator("ensemble", [p1, ..., pK])
    u = estimator(obs)                                       # Uncertainty(mean_action, u_ep, u_al, u_feat)
    u.u_ep_heading, u.u_feat                                 # (B,) arrays
"""

from typing import Any

from socnav.uncertainty.stats import Uncertainty, ensemble_feature_uncertainty, feature_uncertainty, summarise_samples
from socnav.uncertainty.window import WindowedUncertainty

#: Seed of the MC-dropout masks of socnav's experiments and commands: a study, a calibration or an animation gives the
#: same numbers run to run.
MC_SEED = 0

# The estimators (torch) load on first use, so that the NumPy-only parts above (and `socnav.uncertainty.stats`,
# which the torch-free runtime imports) do not pull in torch.
_LAZY = {
    "ESTIMATOR_KINDS": "socnav.uncertainty.estimators",
    "EnsembleEstimator": "socnav.uncertainty.estimators",
    "MCDropoutEstimator": "socnav.uncertainty.estimators",
    "make_estimator": "socnav.uncertainty.estimators",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'socnav.uncertainty' has no attribute {name!r}")


__all__ = [
    "ESTIMATOR_KINDS",
    "MC_SEED",
    "EnsembleEstimator",
    "MCDropoutEstimator",
    "Uncertainty",
    "WindowedUncertainty",
    "ensemble_feature_uncertainty",
    "feature_uncertainty",
    "make_estimator",
    "summarise_samples",
]
