"""An alias module: the names of `spherejax.estimation` under `spherejax.wiener_estimation`,
for code that imports them from here. No code of its own; new code imports from
`spherejax.estimation` (or `spherejax`).

Two names differ from the package's: `METHODS` here is the tuple of accepted method names
(`spherejax.estimation.METHOD_NAMES`; `spherejax.estimation.METHODS` is the mapping from name to
fit), and `wiener_loo_errors`, `select_wiener_noise_variance` and `wiener_from_sensitivity`, the
offset-free baseline estimators (`spherejax.estimation._offset_free`), are importable from here
though not among the package's names.
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
from .estimation._offset_free import select_wiener_noise_variance, wiener_from_sensitivity, wiener_loo_errors

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
