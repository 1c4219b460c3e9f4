"""Parameter estimation for the polynomial model structures (the course notes (Modelling and
Simulation), §4.2–4.6), one module per job:

* :mod:`.fit`: the entry point :func:`fit` (argument checks, dispatch, diagnostics);
* :mod:`.least_squares`: ``"lls"`` and instrumental variables (eq. 4.101, 4.111–4.112);
* :mod:`.prediction_error`: Levenberg–Marquardt on prediction errors and maximum likelihood
  (eq. 3.61, 4.130–4.133);
* :mod:`.initial`: stable starting points for OE, ARMAX, BJ;
* :mod:`.losses`: the per-sample losses of maximum likelihood (eq. 4.64, 4.71–4.75, Huber);
* :mod:`.results`: :class:`FitResult` and the asymptotic covariance;
* :mod:`.uniform_noise`: the uniform-noise maximum-likelihood polytope (eq. 4.58).
"""

from .fit import METHODS, fit
from .losses import LOSSES, FairLoss, GaussianLoss, HuberLoss, LaplaceLoss, make_loss, robust_scale
from .results import STATIONARY_TOL, FitResult, covariance
from .uniform_noise import UniformNoiseSet, uniform_noise_mle_set

__all__ = [
    "LOSSES",
    "METHODS",
    "STATIONARY_TOL",
    "FairLoss",
    "FitResult",
    "GaussianLoss",
    "HuberLoss",
    "LaplaceLoss",
    "UniformNoiseSet",
    "covariance",
    "fit",
    "make_loss",
    "robust_scale",
    "uniform_noise_mle_set",
]
