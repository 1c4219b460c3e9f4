"""The result of :func:`sysid.estimation.fit` and the asymptotic covariance of an estimate
(the course notes (Modelling and Simulation), §4.4-4.6).

For a prediction-error / M-estimate with residual Jacobian ``J`` the covariance is
``factor (J'J)^{-1}`` (the ``sigma^2 (M'M)^{-1}`` form of eq. 4.101): ``factor = sigma^2`` for
least squares, Huber's sandwich ``E[psi^2] / E[psi']^2`` for the fair and Huber losses and
``1 / (4 f(0)^2)`` for least absolute deviations (:func:`covariance`).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.stats
import torch

from ..errors import PoorExcitationWarning
from ..models import PolynomialModel

__all__ = [
    "STATIONARY_TOL",
    "FitResult",
    "covariance",
    "inverse_normal_matrix_and_rank",
    "remaining_step",
]

#: An iterative estimate counts as converged when the Newton/Gauss–Newton step from it
#: (the step to the stationary point of the local quadratic model of the criterion) is
#: shorter than this many standard errors, measured in the estimate's own covariance:
#: ``z = sqrt(d' Cov^{-1} d) <= STATIONARY_TOL``. The numerical error is then a small part
#: of the statistical one. (At a true optimum ``z`` is ~1e-5 in float64 and ~1e-2 in
#: float32; an estimate stopped on the stability boundary, e.g. an output-error model of an
#: unstable plant, has ``z`` of several units.)
STATIONARY_TOL = 0.1


@dataclass
class FitResult:
    """Estimate of :func:`fit` for a (batch of) data set(s).

    Attributes:
        theta: estimate, ``(*batch, p)`` (ordered as ``parameter_names``).
        covariance: asymptotic covariance of ``theta``, ``(*batch, p, p)``.
        standard_errors: ``sqrt(diag(covariance))``, ``(*batch, p)``.
        sigma2: noise variance estimate ``sum r^2 / (N - p)``, ``(*batch,)`` (iterative fits:
            ``N - rank J``, which is ``p`` unless some parameters are not identifiable).
        loss_history: criterion value per iteration of the last stage of the fit,
            ``(n_last + 1, *batch)`` (the value ``sum rho(r_k)``, e.g. ``1/2 ||r||^2`` for the
            Gaussian loss): an iterative fit with another loss starts with Gaussian
            iterations, a grey-box fit by multiple shooting runs penalty stages before its
            simulation criterion; ``iterations`` counts every stage, ``loss_history`` holds
            the reported criterion's only (the earlier stages minimise other functions).
        iterations: iterations used per data set, ``(*batch,)`` int64.
        converged: per data set, ``(*batch,)`` bool: for the iterative methods, whether the
            estimate is a stationary point of the criterion to within
            :data:`STATIONARY_TOL` standard errors (``info["step_in_standard_errors"]``),
            whatever stopped the iteration (for grey-box models, not where a bounded
            parameter stalled at its bound while the criterion decreases inside: a member
            whose estimate rests at a bound with the criterion increasing inside is converged
            and flagged by ``info["at_bound"]``, ``(*batch, p)``); always True for the direct
            solves (``"lls"``, ``"iv"``). ``info["iteration_limit_reached"]`` flags the fits
            that ended on ``max_iter``: an estimate drifting where the criterion keeps falling
            slowly (towards a minimum at infinity, its standard errors growing with it) counts
            as converged by this local test; check that flag and the size of the standard
            errors, or fit from another start.
        method, loss: as requested.
        parameter_names: names of the entries of ``theta``.
        n_samples: number of residuals in the criterion.
        residuals: final residuals (prediction errors ``y - yhat`` or regression residuals),
            ``(*batch, n_samples)``.
        model: the fitted model: a copy of the input model (batched like the data) with the
            estimate as its parameters; the input model is never modified. A grey-box
            model's ``x0`` is the initial state the fit used: the estimates for
            ``x0="estimate"`` (the measured first states for the one-step criterion), a list
            with one per experiment where the data has several, so that
            ``result.model.simulate(data)`` reproduces the fitted simulation.
        info: extra per-method statistics (condition numbers, damping, largest pole
            modulus, ...).
        stable: per data set, ``(*batch,)`` bool: every pole of the estimated model (roots
            of A, D and every F_i) strictly inside the unit circle; where False its
            free-run simulation diverges.
        messages: one line per data set that did not converge or whose estimate is
            unstable, naming its batch index and the reason (also issued as
            :class:`ConvergenceWarning` / :class:`UnstableModelWarning`).
        quality: grey-box fits: :class:`~sysid.validation.FitQuality` (fit %, RMSE, R^2
            per data set and output channel) of the fitted model's free-run simulation on
            the estimation data, from the estimated (or given) initial states; None for
            the polynomial models (use :meth:`validate`).
    """

    theta: torch.Tensor
    covariance: torch.Tensor
    standard_errors: torch.Tensor
    sigma2: torch.Tensor
    loss_history: torch.Tensor
    iterations: torch.Tensor
    converged: torch.Tensor
    method: str
    loss: str
    parameter_names: list[str]
    n_samples: int
    residuals: torch.Tensor
    model: PolynomialModel | None = None
    info: dict = field(default_factory=dict)
    stable: torch.Tensor | None = None
    messages: list[str] = field(default_factory=list)
    quality: object | None = None

    def validate(self, data, skip: int = 0, x0=None):
        """Fit %, RMSE and R^2 (:class:`~sysid.validation.FitQuality`, per data set and output
        channel) of the fitted model's free-run simulation on ``data`` (e.g. validation data),
        leaving out the first ``skip`` samples of every experiment, where the unknown initial
        state still shows.

        ``x0``: grey-box models: the initial state on ``data``, (nx,) / (*batch, nx) or one per
        experiment (a list); None starts from zeros (an initial state estimated by the fit
        belongs to the estimation data: ``result.quality`` holds the statistics there).
        Polynomial models always start from rest.
        """
        from ..continuous.greybox import GreyBoxModel
        from ..validation import fit_quality

        if isinstance(self.model, GreyBoxModel):
            from ..continuous.fit import simulation_quality

            start = torch.zeros(self.model.nx, dtype=torch.float64) if x0 is None else x0
            return simulation_quality(self.model, data, None, start, skip)
        keep = data.samples_after(skip)
        with torch.no_grad():
            yhat = self.model.predict(data, horizon=math.inf)
        quality = fit_quality(data.y.index_select(-2, keep), yhat.index_select(-2, keep))
        quality.skip = skip
        return quality

    @property
    def batch_shape(self) -> torch.Size:
        return self.theta.shape[:-1]

    def summary(self, index: int | tuple[int, ...] | None = None, level: float = 0.95) -> str:
        """A statsmodels-like text table for one data set of the batch.

        Args:
            index: batch index (default: the first data set).
            level: confidence level of the intervals (normal approximation).
        """
        if index is None:
            index = (0,) * len(self.batch_shape)
        index = index if isinstance(index, tuple) else (index,)
        th = self.theta[index].detach().cpu().double()
        se = self.standard_errors[index].detach().cpu().double()
        z = th / se
        p = 2 * scipy.stats.norm.sf(np.abs(z.numpy()))
        q = scipy.stats.norm.ppf(0.5 + level / 2)
        lo, hi = th - q * se, th + q * se
        title = f"{type(self.model).__name__ if self.model is not None else 'Model'} fit"
        width = 78
        lines = [
            title.center(width),
            "=" * width,
            f"{'Method:':<16}{self.method:<23}{'Loss:':<16}{self.loss}",
            f"{'Samples:':<16}{self.n_samples:<23}{'Parameters:':<16}{len(self.parameter_names)}",
            f"{'Criterion:':<16}{float(self.loss_history[-1][index]):<23.6g}"
            f"{'sigma^2:':<16}{float(self.sigma2[index]):.6g}",
            f"{'Iterations:':<16}{int(self.iterations[index]):<23}"
            f"{'Converged:':<16}{bool(self.converged[index])}",
            f"{'Stable:':<16}{str(self.stable is None or bool(self.stable[index])):<23}",
            f"{'Batch index:':<16}{str(index):<23}{'Batch shape:':<16}{tuple(self.batch_shape)}",
            "-" * width,
            f"{'':<10} {'coef':>10} {'std err':>10} {'z':>8} {'P>|z|':>8}"
            f" {f'[{(1 - level) / 2:.3f}':>12} {f'{(1 + level) / 2:.3f}]':>12}",
            "-" * width,
        ]
        for j, name in enumerate(self.parameter_names):
            lines.append(
                f"{name:<10} {th[j].item():>10.4g} {se[j].item():>10.4g} {z[j].item():>8.4g}"
                f" {p[j]:>8.3f} {lo[j].item():>12.4g} {hi[j].item():>12.4g}"
            )
        lines.append("=" * width)
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (
            f"FitResult(method={self.method!r}, loss={self.loss!r}, batch_shape="
            f"{tuple(self.batch_shape)}, p={len(self.parameter_names)}, converged="
            f"{int(self.converged.sum())}/{self.converged.numel()})"
        )


def inverse_normal_matrix_and_rank(J: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(J'J)^{-1}`` via Cholesky of the equilibrated ``J'J``; ``inf`` where not estimable.

    A parameter the residuals do not depend on at all (a zero column of ``J``, e.g. ARMAX's
    C under the simulation criterion) gets ``inf`` in its row and column only: the others'
    covariance is that of the fit without it. Where ``J'J`` is singular (only a combination of
    some parameters reaches the residuals, e.g. ``a1 + a2``), the parameters with a component
    along its null space get ``inf`` rows and columns; the others are estimable (their unit
    vector lies in the row space of ``J``) and keep the finite entries of the pseudo-inverse,
    which every generalised inverse shares for them.

    Returns the matrix (*batch, p, p) and the rank of ``J`` (*batch,) that decides it (``p``
    where ``J`` is not finite)."""
    H = J.transpose(-1, -2) @ J
    diag = torch.diagonal(H, dim1=-2, dim2=-1)
    d = diag.clamp_min(torch.finfo(J.dtype).tiny).rsqrt()
    Hs = H * d.unsqueeze(-1) * d.unsqueeze(-2)
    eye = torch.eye(H.shape[-1], dtype=J.dtype, device=J.device).expand_as(H)
    unused = diag == 0
    unused_entries = unused.unsqueeze(-1) | unused.unsqueeze(-2)
    Hs = torch.where(unused_entries, eye, Hs)
    # a Jacobian with inf/NaN entries (an estimate that ran off to a degenerate model) is
    # singular; the identity stands in for it so the batched factorisations still run
    finite = torch.isfinite(Hs).flatten(-2).all(-1)
    Hs = torch.where(finite[..., None, None], Hs, eye)
    L, info = torch.linalg.cholesky_ex(Hs)
    P = torch.cholesky_solve(eye, L)
    ev, V = torch.linalg.eigh(Hs)
    null = ev <= ev[..., -1:] * torch.finfo(J.dtype).eps * J.shape[-2]  # (*batch, p)
    rank_deficient = null.any(-1) | (info != 0)
    if bool(rank_deficient.any()):
        kept = torch.where(null, torch.zeros_like(ev), 1.0 / torch.where(null, 1.0, ev))
        pinv = (V * kept.unsqueeze(-2)) @ V.transpose(-1, -2)
        # a parameter is estimable where its unit vector has no component along the null space
        along_null = (V * V * null.unsqueeze(-2)).sum(-1)  # (*batch, p)
        not_estimable = along_null > torch.finfo(J.dtype).eps ** 0.5
        pinv = torch.where(
            not_estimable.unsqueeze(-1) | not_estimable.unsqueeze(-2), math.inf, pinv
        )
        P = torch.where(rank_deficient[..., None, None], pinv, P)
    P = P * d.unsqueeze(-1) * d.unsqueeze(-2)
    P = torch.where(unused_entries, math.inf, P)
    P = torch.where(finite[..., None, None], P, torch.full_like(P, math.inf))
    flagged = ~finite | rank_deficient | unused.any(-1)
    if bool(flagged.any()):
        idx = tuple(int(i) for i in torch.nonzero(flagged)[0]) if flagged.dim() else ()
        warnings.warn(
            f"the Jacobian is rank deficient at batch index {idx} ({int(flagged.sum())} data "
            "sets): some parameters are not identifiable from these data (poor excitation, "
            "pole-zero cancellation, or a parameter the criterion does not depend on); their "
            "covariance is reported as inf. Lower the orders or use a richer input.",
            PoorExcitationWarning,
            stacklevel=3,
        )
    rank = J.shape[-1] - null.sum(-1) - unused.sum(-1)
    return P, torch.where(finite, rank, J.shape[-1])


def covariance(
    J: torch.Tensor, r: torch.Tensor, loss
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Asymptotic covariance ``factor (J'J)^{-1}`` of an M-estimate, the residual variance
    ``sum r^2/(M - rank J)`` and ``factor`` (all ``(*batch, ...)``).

    ``loss`` is one of :mod:`sysid.estimation.losses`. Gaussian: ``sigma^2 (J'J)^{-1}``. Fair
    and Huber: Huber's sandwich ``E[psi^2] / E[psi']^2 (J'J)^{-1}`` with sample moments
    (``M - rank J`` in the mean of ``psi^2``). Laplace: the least-absolute-
    deviations law ``(J'J)^{-1} / (4 f(0)^2)`` with the residual density at 0 from a Gaussian
    kernel estimate (Silverman bandwidth).
    """
    M = J.shape[-2]
    P, rank = inverse_normal_matrix_and_rank(J)
    dof = (M - rank).to(J.dtype)
    sigma2 = (r * r).sum(-1) / dof
    if loss.name == "gaussian":
        factor = sigma2
    elif loss.name in ("fair", "huber"):
        psi = loss.psi(r)
        if loss.name == "fair":  # psi' of rho = r^2 / (2 (1 + alpha|r|)): the curvature
            dpsi = loss.curvature(r).mean(-1)
        else:
            dpsi = loss.psi_derivative(r).mean(-1)
        factor = (psi * psi).sum(-1) / dof / dpsi**2
    else:
        std = r.std(dim=-1)
        iqr = (r.quantile(0.75, dim=-1) - r.quantile(0.25, dim=-1)) / 1.349
        h = 0.9 * torch.minimum(std, iqr) * M ** (-0.2)
        f0 = torch.exp(-0.5 * (r / h.unsqueeze(-1)) ** 2).mean(-1) / (h * math.sqrt(2 * math.pi))
        factor = 1.0 / (4 * f0 * f0)
    return factor[..., None, None] * P, sigma2, factor


def remaining_step(
    J: torch.Tensor, r: torch.Tensor, loss, factor: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The undamped step ``d = -H^+ g`` of the iteration's quadratic model at the estimate
    (``H = J'CJ``, ``g = J' psi(r)``, see :func:`integrators.newton.minimize`) and its length in
    standard errors ``z = sqrt(d' Cov^{-1} d) = ||J d|| / sqrt(factor)`` for the covariance
    ``factor (J'J)^{-1}`` of :func:`covariance`. Returns ``d`` ``(*batch, p)`` and ``z``
    ``(*batch,)``; the pseudo-inverse leaves unidentifiable directions (``H`` singular) out."""
    Jt = J.transpose(-1, -2)
    H = Jt @ (J * loss.curvature(r).unsqueeze(-1))
    g = Jt @ loss.psi(r).unsqueeze(-1)
    d = -(torch.linalg.pinv(H, hermitian=True) @ g)
    z = (J @ d).squeeze(-1).norm(dim=-1) / factor.sqrt()
    return d.squeeze(-1), z
