"""Uncertainty estimation for socnav policies: MC-dropout and deep ensembles (paper IV-B, SPEC section 4).
Epistemic / aleatoric uncertainty per action dimension, predictive feature uncertainty, and their windowed mean.

Example::

    from socnav.uncertainty import make_estimator, WindowedUncertainty

    estimator = make_estimator("mc", policy, k=20)          # or make_estimator("ensemble", [p1, ..., pK])
    u = estimator(obs)                                       # Uncertainty(mean_action, u_ep, u_al, u_feat)
    u.u_ep_heading, u.u_feat                                 # (B,) arrays
"""

from socnav.uncertainty.estimators import (
    ESTIMATOR_KINDS,
    EnsembleEstimator,
    MCDropoutEstimator,
    Uncertainty,
    ensemble_feature_uncertainty,
    feature_uncertainty,
    make_estimator,
    summarise_samples,
)
from socnav.uncertainty.window import WindowedUncertainty

__all__ = [
    "ESTIMATOR_KINDS",
    "EnsembleEstimator",
    "MCDropoutEstimator",
    "Uncertainty",
    "WindowedUncertainty",
    "ensemble_feature_uncertainty",
    "feature_uncertainty",
    "make_estimator",
    "summarise_samples",
]
