"""Per-sample losses of the maximum-likelihood estimators (the course notes (Modelling and
Simulation), §4.3, eq. 4.64 and 4.71-4.75).

Each loss has ``rho(r)`` (the per-residual criterion, ``~ r^2 / 2`` near 0), ``psi(r) = rho'(r)``
and ``curvature(r)``: the weights ``c_k`` of the quadratic model ``sum c_k (r_k + J_k d)^2 / 2``
minimised for each step (the loss protocol of :func:`integrators.newton.minimize`); each
also takes ``members``, the data sets of a batch to evaluate (``minimize(compact=True)``;
None for all), for which a per-data-set parameter ``(*batch, 1)`` gives its rows. The
criterion of a fit is ``sum_k rho(r_k)``; for i.i.d. errors of density ``p`` with
``-log p = rho / sigma^2 + const`` its minimiser is the maximum-likelihood estimate.

* :class:`GaussianLoss`: ``rho = r^2 / 2`` (weighted least squares, eq. 4.64), ``c = 1``
  (Gauss-Newton).
* :class:`FairLoss`: the fair density, see below; ``c = rho''`` (Newton for linear models).
* :class:`LaplaceLoss`: least absolute deviations, smoothed, see below; ``c = psi(r)/r``
  (iteratively reweighted least squares).
* :class:`HuberLoss`: Huber's ``rho = r^2/2`` for ``|r| <= c`` and ``c|r| - c^2/2`` beyond,
  the maximum-likelihood criterion of Huber's least-favourable density (Gaussian centre,
  Laplace tails); ``c = psi(r)/r = min(1, c/|r|)`` (IRLS, whose quadratic model majorises
  ``rho``, so every full step decreases the criterion).

On the fair loss (checked): the density (4.71) ``p(x) ∝ exp(-x^2 / (2 sigma^2 (1 + alpha|x|)))``
gives, by ``-log``, the criterion (4.73) ``sum r_k^2 / (1 + alpha |r_k|) / (2 sigma^2)``
(correct). Eq. (4.74) then drops a square: with ``||x||_Fair`` defined as the square root in
(4.75), the criterion is ``||r||_Fair^2 / (2 sigma^2)`` (typo in the notes). The minimiser does
not depend on ``sigma`` but does on ``alpha`` (units 1/output). ``rho(r) = r^2 / (2 (1 +
alpha|r|))`` (the Gaussian loss's ``r^2 / 2`` at ``alpha = 0``) is convex (``rho'' = 1 / (1 +
alpha|r|)^3 > 0``) and grows like ``|r| / (2 alpha)``: Gaussian near 0,
Laplace-like tails, so a Newton iteration with line search finds the unique minimiser of the
linear-in-theta problem. (It is not the "Fair" function of robust statistics,
``c^2 (|r|/c - log(1 + |r|/c))``, although both are quadratic near 0 and linear in the tails.)

On the Laplace loss: ``sum |r_k|`` is not differentiable where a residual is zero, which is
exactly where the optimum of a least-absolute-deviations problem sits (it interpolates ``p``
samples). We minimise the smoothed ``sum sqrt(r_k^2 + eps^2)`` by iteratively reweighted
least squares: the weights ``1/sqrt(r_k^2 + eps^2)`` give the majorising quadratic of the
smoothed loss at the current point, so each full step decreases it (a majorise–minimise
iteration, monotone and globally convergent for the convex linear-in-theta problem), and its
minimiser is within ``N eps`` in loss of the exact LAD optimum. ``eps`` is ``1e-4`` times a
robust scale of the initial residuals.
"""

from __future__ import annotations

import torch

from integrators.errors import InputValidationError

__all__ = [
    "LOSSES",
    "FairLoss",
    "GaussianLoss",
    "HuberLoss",
    "LaplaceLoss",
    "make_loss",
    "robust_scale",
]

#: Names accepted by ``fit(loss=...)`` and :func:`make_loss`.
LOSSES = ("gaussian", "fair", "laplace", "huber")

#: Huber's tuning constant in units of the robust scale: 95 % efficiency at the Gaussian.
HUBER_EFFICIENT_C = 1.345


def _member_rows(param, members: torch.Tensor | None):
    """A loss parameter for the problems ``members`` ((k,) indices into the flattened batch):
    the rows ``(k, 1)`` of a per-data-set ``(*batch, 1)`` tensor; a number, a 0-d tensor, or
    any parameter for ``members=None``, as it is."""
    if members is None or not isinstance(param, torch.Tensor) or param.dim() == 0:
        return param
    return param.reshape(-1, 1)[members]


class GaussianLoss:
    """``rho(r) = r^2 / 2``, ``psi(r) = r``, curvature 1 (Gauss-Newton)."""

    name = "gaussian"

    def rho(self, r: torch.Tensor, members=None) -> torch.Tensor:
        return 0.5 * r * r

    def psi(self, r: torch.Tensor, members=None) -> torch.Tensor:
        return r

    def curvature(self, r: torch.Tensor, members=None) -> torch.Tensor:
        return torch.ones_like(r)


class FairLoss:
    """``rho(r) = r^2 / (2 (1 + alpha |r|))`` (eq. 4.73), curvature ``rho'' = 1/(1 + alpha|r|)^3``.

    Args:
        alpha: > 0, units 1/output; a scalar or a tensor broadcasting against the residuals
            (e.g. ``(*batch, 1)``, one value per data set).
    """

    name = "fair"

    def __init__(self, alpha):
        self.alpha = alpha

    def rho(self, r: torch.Tensor, members=None) -> torch.Tensor:
        return 0.5 * r * r / (1 + _member_rows(self.alpha, members) * r.abs())

    def psi(self, r: torch.Tensor, members=None) -> torch.Tensor:
        s = _member_rows(self.alpha, members) * r.abs()
        return 0.5 * r * (2 + s) / (1 + s) ** 2

    def curvature(self, r: torch.Tensor, members=None) -> torch.Tensor:
        return 1.0 / (1 + _member_rows(self.alpha, members) * r.abs()) ** 3


class LaplaceLoss:
    """Smoothed absolute value ``rho(r) = sqrt(r^2 + eps^2) - eps``, IRLS curvature
    ``psi(r)/r = 1/sqrt(r^2 + eps^2)``.

    Args:
        eps: > 0, output units; scalar or broadcasting against the residuals.
    """

    name = "laplace"

    def __init__(self, eps):
        self.eps = eps

    def rho(self, r: torch.Tensor, members=None) -> torch.Tensor:
        eps = _member_rows(self.eps, members)
        return torch.sqrt(r * r + eps**2) - eps

    def psi(self, r: torch.Tensor, members=None) -> torch.Tensor:
        return r / torch.sqrt(r * r + _member_rows(self.eps, members) ** 2)

    def curvature(self, r: torch.Tensor, members=None) -> torch.Tensor:
        return 1.0 / torch.sqrt(r * r + _member_rows(self.eps, members) ** 2)


class HuberLoss:
    """Huber's loss ``rho(r) = r^2/2`` (``|r| <= c``), ``c|r| - c^2/2`` (beyond);
    ``psi(r) = clamp(r, -c, c)``; IRLS curvature ``psi(r)/r = min(1, c/|r|)``.

    Args:
        c: > 0, output units (the residual size where the loss turns linear); scalar or
            broadcasting against the residuals.
    """

    name = "huber"

    def __init__(self, c):
        self.c = c

    def rho(self, r: torch.Tensor, members=None) -> torch.Tensor:
        a, c = r.abs(), _member_rows(self.c, members)
        return torch.where(a <= c, 0.5 * r * r, c * a - 0.5 * c * c)

    def psi(self, r: torch.Tensor, members=None) -> torch.Tensor:
        c = torch.as_tensor(_member_rows(self.c, members), dtype=r.dtype, device=r.device)
        return torch.maximum(torch.minimum(r, c), -c)

    def curvature(self, r: torch.Tensor, members=None) -> torch.Tensor:
        return torch.clamp(_member_rows(self.c, members) / r.abs(), max=1.0)

    def psi_derivative(self, r: torch.Tensor) -> torch.Tensor:
        """``psi'(r)``: 1 inside ``[-c, c]``, 0 outside (for the sandwich covariance)."""
        return (r.abs() <= self.c).to(r.dtype)


def robust_scale(r: torch.Tensor) -> torch.Tensor:
    """``1.4826 * median(|r - median r|)`` along the last dim (the std for Gaussian data); the
    median of an even count is the mean of the two middle values (``torch.median`` gives the
    lower one)."""
    med = torch.quantile(r, 0.5, dim=-1, keepdim=True)
    return 1.4826 * torch.quantile((r - med).abs(), 0.5, dim=-1)


def make_loss(name: str, residuals: torch.Tensor, alpha=None):
    """The loss ``name`` scaled to ``residuals`` (``(*batch, M)``, e.g. those of a
    least-squares fit), with ``s`` their :func:`robust_scale` (``(*batch,)``):

    * ``"gaussian"``: :class:`GaussianLoss` (no scale);
    * ``"fair"``: :class:`FairLoss` with ``alpha`` (scalar or ``(*batch,)``), default ``1/s``;
    * ``"laplace"``: :class:`LaplaceLoss` with ``eps = 1e-4 s``;
    * ``"huber"``: :class:`HuberLoss` with ``c = alpha`` (output units) if given, else
      ``c = 1.345 s`` (95 % efficiency for Gaussian errors).

    Per-data-set parameters are expanded to ``(*batch, 1)``, so they broadcast against the
    residuals and give each data set's rows.
    """
    if name == "gaussian":
        return GaussianLoss()
    if name not in LOSSES:
        raise InputValidationError(f"loss must be one of {LOSSES}, got {name!r}.")
    scale = robust_scale(residuals).clamp_min(torch.finfo(residuals.dtype).tiny)
    to = dict(dtype=residuals.dtype, device=residuals.device)
    batch = residuals.shape[:-1]
    if name == "laplace":
        return LaplaceLoss((1e-4 * scale).unsqueeze(-1))
    if name == "fair":
        a = (1.0 / scale) if alpha is None else torch.as_tensor(alpha, **to)
        return FairLoss(a.expand(batch).unsqueeze(-1) if a.dim() else a)
    c = HUBER_EFFICIENT_C * scale if alpha is None else torch.as_tensor(alpha, **to)
    return HuberLoss(c.expand(batch).unsqueeze(-1) if c.dim() else c)
