"""Kept for existing imports: the estimators now live in `spherejax.estimation`, a module per
method (`regression`, `haneishi2000`), `cross_validation`, `covariance` and `METHODS`.

Everything this module held is re-exported under its old name, so that
`spherejax.wiener_estimation.X` keeps working; new code imports from `spherejax.estimation` (or
`spherejax`). Two differences of meaning: `METHODS` here is still the tuple of accepted method
names (`spherejax.estimation.METHOD_NAMES`; `spherejax.estimation.METHODS` is the mapping from
name to fit), and the first release's `wiener_loo_errors`, `select_wiener_noise_variance` and
`wiener_from_sensitivity`, kept only to reproduce its results, are no longer public
(`spherejax.estimation._first_release`) but still importable from here.
"""

from __future__ import annotations

from .estimation import (  # DEFAULT_FOLDS, MARKOV_PRIOR_CORRELATION: names it had outside __all__
    DEFAULT_FOLDS,  # noqa: F401
    MARKOV_PRIOR_CORRELATION,  # noqa: F401
    METHOD_NAMES as METHODS,
    PRIOR_SHRINKAGE_GRID,
    RELATIVE_NOISE_GRID,
    SENSITIVITY_PENALTIES,
    SENSITIVITY_PENALTY_GRID,
    CrossValidation,
    EstimatorCovariance,
    WienerEstimator,
    as_estimator,
    estimate_system,
    estimator_covariance,
    fit_wiener,
    fold_labels,
    fold_weights,
    markov_correlation,
    model_estimator,
    training_estimator,
    wiener,
    wiener_from_system,
)
from .estimation._first_release import select_wiener_noise_variance, wiener_from_sensitivity, wiener_loo_errors

__all__ = [
    "RELATIVE_NOISE_GRID",
    "SENSITIVITY_PENALTY_GRID",
    "SENSITIVITY_PENALTIES",
    "PRIOR_SHRINKAGE_GRID",
    "METHODS",
    "CrossValidation",
    "EstimatorCovariance",
    "WienerEstimator",
    "as_estimator",
    "estimate_system",
    "estimator_covariance",
    "fit_wiener",
    "fold_labels",
    "fold_weights",
    "markov_correlation",
    "model_estimator",
    "select_wiener_noise_variance",
    "training_estimator",
    "wiener",
    "wiener_from_sensitivity",
    "wiener_from_system",
    "wiener_loo_errors",
]
