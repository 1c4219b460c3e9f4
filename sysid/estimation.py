"""Parameter estimation for the polynomial model structures (notes §4.2–4.6).

:func:`fit` is the single entry point (model → data → estimate → :class:`FitResult`):

* ``method="lls"`` (FIR, ARX): the prediction-error method is a linear least-squares problem,
  ``theta = argmin 1/2 ||M theta - y||^2`` with the regressor ``M`` of eq. 4.111 (eq. 4.112),
  solved by :func:`sysid.lls.lls` with covariance ``sigma^2 (M'M)^{-1}`` (eq. 4.101 form).
* ``method="iv"`` (ARX structure): instrumental variables. The instruments are the regressors
  built from the noise-free simulated output ``x = B/A u`` of a previous estimate instead of
  the measured ``y``, so they are uncorrelated with coloured equation errors; the estimate is
  consistent where least squares is biased (e.g. white output noise).
* ``method="gauss_newton"``: batched Levenberg–Marquardt (Gauss–Newton with the
  regularisation ``alpha I`` of eq. 3.61 and an Armijo line search) on the prediction errors
  (eq. 4.130–4.132; for OE these are the simulation errors, eq. 4.133). Jacobians by
  forward-mode autograd, all parameter directions in one pass; per-data-set damping,
  step acceptance and convergence. Steps that make the predictor unstable are rejected.
  Asymptotic covariance ``sigma^2 (J'J)^{-1}``.
* ``method="mle"``: maximum likelihood for a noise model: ``loss="gaussian"`` (weighted least
  squares, eq. 4.64; known per-sample variances via ``weights = 1/sigma_k^2``), ``"fair"``
  (eq. 4.73) or ``"laplace"`` (least absolute deviations). Linear-in-theta models use the
  regression form, the others the prediction errors; the same Levenberg–Marquardt engine
  minimises the sum of the per-sample losses with curvature weights (see ``_Loss``).

On the fair loss (checked): the density (4.71) ``p(x) ∝ exp(-x^2 / (2 sigma^2 (1 + alpha|x|)))``
gives, by ``-log``, the criterion (4.73) ``sum r_k^2 / (1 + alpha |r_k|) / (2 sigma^2)``
(correct). Eq. (4.74) then drops a square: with ``||x||_Fair`` defined as the square root in
(4.75), the criterion is ``||r||_Fair^2 / (2 sigma^2)`` (typo in the notes). The minimiser does
not depend on ``sigma`` but does on ``alpha`` (units 1/output). ``rho(r) = r^2 / (1 + alpha|r|)``
is convex (``rho'' = 2 / (1 + alpha|r|)^3 > 0``) and grows like ``|r| / alpha``: Gaussian near 0,
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

For a linear-in-theta model with uniform noise on ``[-a, a]`` (eq. 4.43–4.45) the maximum-
likelihood estimates form a polytope (eq. 4.58); :func:`uniform_noise_mle_set` returns it with
per-parameter bounds from linear programs.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.optimize
import scipy.stats
import torch
import torch.autograd.forward_ad as fwAD
import torch.nn.functional as F

from integrators.errors import (
    ConvergenceWarning,
    InputValidationError,
    PoorExcitationWarning,
    SingularMatrixError,
    UnstableModelWarning,
)

from .data import IOData
from .filters import iir_filter
from .lls import lls
from .models import ARX, PolynomialModel

__all__ = [
    "FitResult",
    "UniformNoiseSet",
    "fit",
    "uniform_noise_mle_set",
]

METHODS = ("lls", "gauss_newton", "mle", "iv")
LOSSES = ("gaussian", "fair", "laplace")

#: An iterative estimate counts as converged when the Newton/Gauss–Newton step from it
#: (the step to the stationary point of the local quadratic model of the criterion) is
#: shorter than this many standard errors, measured in the estimate's own covariance:
#: ``z = sqrt(d' Cov^{-1} d) <= STATIONARY_TOL``. The numerical error is then a small part
#: of the statistical one. (At a true optimum ``z`` is ~1e-5 in float64 and ~1e-2 in
#: float32; an estimate stopped on the stability boundary, e.g. an output-error model of an
#: unstable plant, has ``z`` of several units.)
STATIONARY_TOL = 0.1

#: Largest pole modulus above which a non-converged estimate is reported as sitting on the
#: stability boundary (the Levenberg–Marquardt steps keep it strictly inside), as is one
#: whose step to the stationary point leads to an unstable predictor.
_BOUNDARY_MODULUS = 0.99


# ---------------------------------------------------------------------------- losses
class _Loss:
    """Per-sample loss ``rho(r)`` (``~ r^2 / 2`` near 0), ``psi = rho'`` and curvature weights.

    ``curvature(r)`` are the weights ``c_k`` of the quadratic model
    ``sum c_k (r_k + J_k d)^2 / 2`` used for the step: ``1`` (Gauss–Newton) for the Gaussian
    loss, ``rho''`` (Newton for linear models) for the fair loss, and the IRLS/majorising
    weights ``psi(r)/r`` for the smoothed Laplace loss.
    """

    def __init__(
        self, name: str, alpha: torch.Tensor | None = None, eps: torch.Tensor | None = None
    ):
        self.name, self.alpha, self.eps = name, alpha, eps

    def rho(self, r):
        if self.name == "gaussian":
            return 0.5 * r * r
        if self.name == "fair":
            return 0.5 * r * r / (1 + self.alpha * r.abs())
        return torch.sqrt(r * r + self.eps**2) - self.eps

    def psi(self, r):
        if self.name == "gaussian":
            return r
        if self.name == "fair":
            s = self.alpha * r.abs()
            return 0.5 * r * (2 + s) / (1 + s) ** 2
        return r / torch.sqrt(r * r + self.eps**2)

    def curvature(self, r):
        if self.name == "gaussian":
            return torch.ones_like(r)
        if self.name == "fair":
            return 1.0 / (1 + self.alpha * r.abs()) ** 3
        return 1.0 / torch.sqrt(r * r + self.eps**2)


def _robust_scale(r: torch.Tensor) -> torch.Tensor:
    """``1.4826 * median(|r - median r|)`` along the last dim (the std for Gaussian data)."""
    med = r.median(dim=-1, keepdim=True).values
    return 1.4826 * (r - med).abs().median(dim=-1).values


# ---------------------------------------------------------------------------- result
@dataclass
class FitResult:
    """Estimate of :func:`fit` for a (batch of) data set(s).

    Attributes:
        theta: estimate, ``(*batch, p)`` (ordered as ``parameter_names``).
        covariance: asymptotic covariance of ``theta``, ``(*batch, p, p)``.
        standard_errors: ``sqrt(diag(covariance))``, ``(*batch, p)``.
        sigma2: noise variance estimate ``sum r^2 / (N - p)``, ``(*batch,)``.
        loss_history: criterion value per iteration, ``(n_iter + 1, *batch)`` (the value
            ``sum rho(r_k)``, e.g. ``1/2 ||r||^2`` for the Gaussian loss).
        iterations: iterations used per data set, ``(*batch,)`` int64.
        converged: per data set, ``(*batch,)`` bool: for the iterative methods, whether the
            estimate is a stationary point of the criterion to within
            :data:`STATIONARY_TOL` standard errors (``info["step_in_standard_errors"]``),
            whatever stopped the iteration; always True for the direct solves (``"lls"``,
            ``"iv"``).
        method, loss: as requested.
        parameter_names: names of the entries of ``theta``.
        n_samples: number of residuals in the criterion.
        residuals: final residuals (prediction errors or regression residuals),
            ``(*batch, n_samples)``.
        model: the fitted model (the input model updated in place, or a batched copy when
            the model had no batch dimension and the data had one).
        info: extra per-method statistics (condition numbers, damping, largest pole
            modulus, ...).
        stable: per data set, ``(*batch,)`` bool: every pole of the estimated model (roots
            of A, D and every F_i) strictly inside the unit circle; where False its
            free-run simulation diverges.
        messages: one line per data set that did not converge or whose estimate is
            unstable, naming its batch index and the reason (also issued as
            :class:`ConvergenceWarning` / :class:`UnstableModelWarning`).
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


# ---------------------------------------------------------------------------- helpers
def _batched_model(model: PolynomialModel, batch_shape: torch.Size) -> PolynomialModel:
    """``model`` itself when its batch matches the data, else a batched copy of an unbatched one."""
    if model.batch_shape == batch_shape:
        return model
    if model.batch_shape != torch.Size([]):
        raise InputValidationError(
            f"the model's batch shape {tuple(model.batch_shape)} does not match the data's "
            f"{tuple(batch_shape)}; build the model with batch_shape={tuple(batch_shape)} or "
            "without a batch shape."
        )
    new = _copy_model(model, batch_shape)
    new.set_parameter_vector(model.parameter_vector().detach())
    return new


def _groups(model: PolynomialModel) -> dict[str, list[list[int]]]:
    """Indices into ``theta`` of each polynomial, by letter (one list per input for b, f)."""
    out: dict[str, list[list[int]]] = {}
    for j, name in enumerate(model.parameter_names()):
        letter = name[0]
        suffix = name.split("_")[1] if "_" in name else ""
        key = letter + suffix
        out.setdefault(key, []).append(j)
    grouped: dict[str, list[list[int]]] = {k: [] for k in "abcdf"}
    for key, idx in out.items():
        grouped[key[0]].append(idx)
    return grouped


def _max_root_modulus(theta: torch.Tensor, blocks: list[list[int]]) -> torch.Tensor:
    """Largest root modulus of the monic polynomials ``1 + t_1 z^-1 + ...`` (``(*batch,)``)."""
    out = torch.zeros(theta.shape[:-1], dtype=theta.dtype, device=theta.device)
    for idx in blocks:  # loop over polynomials (a handful), never over samples
        n = len(idx)
        tail = theta[..., idx]
        comp = torch.zeros(*theta.shape[:-1], n, n, dtype=theta.dtype, device=theta.device)
        comp[..., 0, :] = -tail
        if n > 1:
            k = torch.arange(n - 1, device=theta.device)
            comp[..., k + 1, k] = 1.0
        out = torch.maximum(out, torch.linalg.eigvals(comp).abs().amax(dim=-1))
    return out


def _jacobian(residual_fn, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Residuals ``(*batch, M)`` and Jacobian ``(*batch, M, p)`` by forward-mode autograd.

    The ``p`` tangent directions are stacked as a leading batch dimension, so one dual pass
    through the (batched) model gives every column; batch members never mix.
    """
    p = theta.shape[-1]
    eye = torch.eye(p, dtype=theta.dtype, device=theta.device)
    tangent = eye.reshape(p, *([1] * (theta.dim() - 1)), p).expand(p, *theta.shape).clone()
    primal = theta.detach().unsqueeze(0).expand(p, *theta.shape).clone()
    with fwAD.dual_level():
        out = residual_fn(fwAD.make_dual(primal, tangent))
        unpacked = fwAD.unpack_dual(out)
        r, jt = unpacked.primal, unpacked.tangent
    if jt is None:
        jt = torch.zeros_like(r)
    return r[0].detach(), jt.movedim(0, -1).detach()


class _OutputError:
    """Simulation errors and their exact Jacobian for models without A, C, D
    (``y = sum_i q^-nk_i B_i/F_i u_i + e``, eq. 4.133), by filtering, no autograd.

    With ``v_i = u_i / F_i`` and ``x_i = B_i / F_i u_i`` (the response to input i),
    ``d yhat / d b_ij = v_i(t - nk_i - j)`` and ``d yhat / d f_ij = -x_i(t - j) / F_i``
    (``d(1/F)/df_j = -q^-j / F^2``); so one more pass of the filter ``1/F_i`` over the two
    signals ``u_i`` and ``x_i`` (one batched call) gives every column; ``J = -d yhat/d theta``
    is then a stack of delayed copies. Zero initial conditions in each experiment,
    experiments concatenated in time; ``sw`` (``(*batch, M)`` or None) weights the rows.

    :meth:`linearise` reuses the responses ``x_i`` of the last :meth:`residuals` call when
    ``theta`` is the same (in Levenberg-Marquardt, the accepted line-search point).
    """

    def __init__(self, model: PolynomialModel, data: IOData, sw: torch.Tensor | None):
        self.model, self.data, self.sw = model, data, sw
        # rows of J' in theta order, by blocks (signal, input, first lag, count): b_i from
        # -v_i (signal 0) delayed by nk_i, nk_i + 1, ..; then f_i from x_i / F_i (signal 1)
        # delayed by 1, 2, ..
        self.blocks = [
            (0, i, k, n) for i, (k, n) in enumerate(zip(model.nk, model.nb, strict=True))
        ]
        self.blocks += [(1, i, 1, n) for i, n in enumerate(model.nf)]
        self.blocks = [block for block in self.blocks if block[3]]
        self.top = max((first + n - 1 for _, _, first, n in self.blocks), default=0)
        self._last: tuple[torch.Tensor, list[torch.Tensor]] | None = None

    def _responses(self, theta: torch.Tensor, B, den) -> list[torch.Tensor]:
        """Per experiment, the responses ``x_i`` ``(*batch, nu, N)``."""
        if self._last is not None and torch.equal(self._last[0], theta):
            return self._last[1]
        out = [
            iir_filter(B, den, part.u.to(theta.dtype).transpose(-1, -2))
            for part in self.data.experiment_list  # loop over experiments (usually one)
        ]
        if not out[0].requires_grad:
            self._last = (theta.detach().clone(), out)
        return out

    def _errors(self, theta: torch.Tensor, responses: list[torch.Tensor]) -> torch.Tensor:
        parts = [
            part.y[..., 0].to(theta.dtype) - x.sum(-2)
            for part, x in zip(self.data.experiment_list, responses, strict=True)
        ]
        r = parts[0] if len(parts) == 1 else torch.cat(parts, dim=-1)
        r = r.expand(*theta.shape[:-1], r.shape[-1])
        return r if self.sw is None else r * self.sw

    def residuals(self, theta: torch.Tensor) -> torch.Tensor:
        """Weighted simulation errors ``(*batch, M)`` (those of ``model.simulation_errors``)."""
        B, den = self.model._transfer_polys(theta)
        return self._errors(theta, self._responses(theta, B, den))

    def linearise(self, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(r, J)``; ``J`` is the transpose of a contiguous ``(*batch, p, M)`` tensor (a
        faster ``J'J``)."""
        with torch.no_grad():
            B, den = self.model._transfer_polys(theta)  # (*b, nu, width), (*b, nu, nf)
            ones = den.new_ones(*den.shape[:-1], 1)  # numerator 1 (den may be empty: nf = 0)
            responses = self._responses(theta, B, den)
            jacobians = []
            for part, x in zip(self.data.experiment_list, responses, strict=True):
                u = part.u.to(theta.dtype).transpose(-1, -2)
                both = torch.stack(torch.broadcast_tensors(-u, x), dim=-3)
                both = iir_filter(ones.unsqueeze(-3), den.unsqueeze(-3), both)  # -v_i, x_i/F_i
                N = both.shape[-1]
                windows = F.pad(both, (self.top, 0)).unfold(-1, N, 1)  # window j: top - j
                # each block is a slice of consecutive windows in decreasing delay: take the
                # blocks in reverse order, then one flip restores theta order
                last = [
                    windows[..., s, i, self.top - first - n + 1 : self.top - first + 1, :]
                    for s, i, first, n in reversed(self.blocks)  # loop over inputs (2 nu)
                ]
                empty = both.new_zeros(*both.shape[:-3], 0, N)  # a model without parameters
                jacobians.append(torch.cat(last, dim=-2).flip(-2) if last else empty)
            Jt = jacobians[0] if len(jacobians) == 1 else torch.cat(jacobians, dim=-1)
            Jt = Jt.expand(*theta.shape[:-1], *Jt.shape[-2:])
            if self.sw is not None:
                Jt = Jt * self.sw.unsqueeze(-2)
            return self._errors(theta, responses), Jt.transpose(-1, -2)


@dataclass
class _LMResult:
    theta: torch.Tensor
    history: torch.Tensor
    iterations: torch.Tensor
    converged: torch.Tensor
    failed: torch.Tensor
    residuals: torch.Tensor
    jacobian: torch.Tensor
    damping: torch.Tensor


def _levenberg_marquardt(
    residual_fn,
    theta0: torch.Tensor,
    loss: _Loss,
    *,
    admissible=None,
    jacobian_fn=None,
    max_iter: int = 100,
    xtol: float = 1e-8,
    ftol: float = 1e-10,
    gtol: float = 1e-12,
    max_backtracks: int = 12,
) -> _LMResult:
    """Batched Levenberg–Marquardt / Gauss–Newton with Armijo backtracking.

    Minimises ``sum_k rho(r_k(theta))`` per batch member. Step:
    ``(J' C J + alpha I) d = -J' psi(r)`` with the curvature weights ``C = loss.curvature(r)``
    and ``alpha = lam * trace(J'CJ) / p`` (eq. 3.61, scaled to the curvature); then
    ``t = 1, 1/2, ...`` until ``f(theta + t d) <= f(theta) + 1e-4 t g'd`` and the candidate is
    admissible (e.g. a stable predictor). ``lam`` shrinks after full steps and grows after
    shortened or failed ones, per batch member; converged members are frozen.

    Args:
        residual_fn: ``theta (*batch, p) -> r (*batch, M)``; must accept dual tensors (forward
            AD) unless ``jacobian_fn`` is given.
        theta0: start, ``(*batch, p)``.
        admissible: optional ``theta -> (*batch,) bool``; inadmissible candidates are rejected.
        jacobian_fn: optional ``theta -> (r, J)``.
    """
    theta = theta0.detach().clone()
    batch = theta.shape[:-1]
    p = theta.shape[-1]
    dtype, device = theta.dtype, theta.device
    eps = torch.finfo(dtype).eps
    xtol, ftol = max(xtol, 10 * eps), max(ftol, 10 * eps)  # reachable in float32 too
    lam = torch.full(batch, 1e-6, dtype=dtype, device=device)
    converged = torch.zeros(batch, dtype=torch.bool, device=device)
    iterations = torch.zeros(batch, dtype=torch.int64, device=device)
    eye = torch.eye(p, dtype=dtype, device=device)

    def evaluate(th):
        with torch.no_grad():
            r = residual_fn(th)
            f = loss.rho(r).sum(-1)
        f = torch.where(torch.isfinite(f), f, torch.full_like(f, math.inf))
        if admissible is not None:
            f = torch.where(admissible(th), f, torch.full_like(f, math.inf))
        return f

    def linearise(th):
        return jacobian_fn(th) if jacobian_fn is not None else _jacobian(residual_fn, th)

    failed = torch.zeros(batch, dtype=torch.bool, device=device)
    r, J = linearise(theta)
    f = loss.rho(r).sum(-1)
    if bool((~torch.isfinite(f)).any()):
        raise InputValidationError(
            "the criterion is not finite at the initial parameters (unstable initial model or "
            "non-finite data); start from a stable model."
        )
    history = [f.clone()]
    for _ in range(max_iter):
        active = ~(converged | failed)
        if not bool(active.any()):
            break
        Jt = J.transpose(-1, -2)
        H = Jt @ J if loss.name == "gaussian" else Jt @ (J * loss.curvature(r).unsqueeze(-1))
        g = (Jt @ loss.psi(r).unsqueeze(-1)).squeeze(-1)
        scale = (torch.diagonal(H, dim1=-2, dim2=-1).sum(-1) / p).clamp_min(torch.finfo(dtype).tiny)
        small_grad = g.abs().amax(-1) <= gtol * (1 + f) * scale.sqrt()
        L, info = torch.linalg.cholesky_ex(H + (lam * scale)[..., None, None] * eye)
        for _ in range(30):  # numerically indefinite: damp those members more
            if not bool((info != 0).any()):
                break
            lam = torch.where(info != 0, lam * 10, lam)
            L, info = torch.linalg.cholesky_ex(H + (lam * scale)[..., None, None] * eye)
        step = -torch.cholesky_solve(g.unsqueeze(-1), L).squeeze(-1)
        slope = (g * step).sum(-1)
        t = torch.ones(batch, dtype=dtype, device=device)
        accepted = torch.zeros(batch, dtype=torch.bool, device=device)
        f_new = f.clone()
        pending = active & ~small_grad
        for _ls in range(max_backtracks):
            if not bool(pending.any()):
                break
            fc = evaluate(theta + t.unsqueeze(-1) * step)
            ok = pending & (fc <= f + 1e-4 * t * slope)
            accepted |= ok
            f_new = torch.where(ok, fc, f_new)
            pending = pending & ~ok
            t = torch.where(pending, 0.5 * t, t)
        full = accepted & (t == 1)
        lam = torch.where(full, (lam / 10).clamp_min(1e-12), lam)
        lam = torch.where(accepted & ~full, lam * 2, lam)
        lam = torch.where(active & ~accepted & ~small_grad, lam * 10, lam)
        move = active & accepted
        dtheta = torch.where(move.unsqueeze(-1), t.unsqueeze(-1) * step, 0.0)
        step_small = dtheta.norm(dim=-1) <= xtol * (xtol + theta.norm(dim=-1))
        f_small = (f - f_new) <= ftol * f
        theta = theta + dtheta
        f = torch.where(move, f_new, f)
        iterations = iterations + active.to(torch.int64)
        converged = converged | (active & (small_grad | (accepted & (step_small | f_small))))
        failed = failed | (active & ~accepted & ~small_grad & (lam > 1e10))
        history.append(f.clone())
        r, J = linearise(theta)
    return _LMResult(
        theta=theta,
        history=torch.stack(history),
        iterations=iterations,
        converged=converged,
        failed=failed,
        residuals=r,
        jacobian=J,
        damping=lam,
    )


# ---------------------------------------------------------------------------- covariance
def _inverse_normal_matrix(J: torch.Tensor) -> torch.Tensor:
    """``(J'J)^{-1}`` via Cholesky of the equilibrated ``J'J``; ``inf`` where singular."""
    H = J.transpose(-1, -2) @ J
    d = torch.diagonal(H, dim1=-2, dim2=-1).clamp_min(torch.finfo(J.dtype).tiny).rsqrt()
    Hs = H * d.unsqueeze(-1) * d.unsqueeze(-2)
    L, info = torch.linalg.cholesky_ex(Hs)
    eye = torch.eye(H.shape[-1], dtype=J.dtype, device=J.device).expand_as(H)
    P = torch.cholesky_solve(eye, L) * d.unsqueeze(-1) * d.unsqueeze(-2)
    ev = torch.linalg.eigvalsh(Hs)
    singular = (info != 0) | (ev[..., 0] <= ev[..., -1] * torch.finfo(J.dtype).eps * J.shape[-2])
    if bool(singular.any()):
        idx = tuple(int(i) for i in torch.nonzero(singular)[0]) if singular.dim() else ()
        warnings.warn(
            f"the Jacobian is rank deficient at batch index {idx} ({int(singular.sum())} data "
            "sets): some parameters are not identifiable from these data (poor excitation or "
            "pole-zero cancellation); their covariance is reported as inf. Lower the orders "
            "or use a richer input.",
            PoorExcitationWarning,
            stacklevel=3,
        )
        P = torch.where(singular[..., None, None], torch.full_like(P, math.inf), P)
    return P


def _covariance(
    J: torch.Tensor, r: torch.Tensor, loss: _Loss
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Asymptotic covariance ``factor (J'J)^{-1}`` of an M-estimate, the residual variance
    ``sum r^2/(M - p)`` and ``factor`` (all ``(*batch, ...)``).

    Gaussian: ``sigma^2 (J'J)^{-1}``. Fair: Huber's sandwich
    ``E[psi^2] / E[psi']^2 (J'J)^{-1}`` with sample moments. Laplace: the least-absolute-
    deviations law ``(J'J)^{-1} / (4 f(0)^2)`` with the residual density at 0 from a Gaussian
    kernel estimate (Silverman bandwidth).
    """
    M, p = J.shape[-2], J.shape[-1]
    sigma2 = (r * r).sum(-1) / (M - p)
    P = _inverse_normal_matrix(J)
    if loss.name == "gaussian":
        factor = sigma2
    elif loss.name == "fair":
        psi = loss.psi(r)
        s = loss.alpha * r.abs()
        dpsi = (1.0 / (1 + s) ** 3).mean(-1)  # psi' of rho = r^2 / (2 (1 + alpha|r|))
        factor = (psi * psi).sum(-1) / (M - p) / dpsi**2
    else:
        std = r.std(dim=-1)
        iqr = (r.quantile(0.75, dim=-1) - r.quantile(0.25, dim=-1)) / 1.349
        h = 0.9 * torch.minimum(std, iqr) * M ** (-0.2)
        f0 = torch.exp(-0.5 * (r / h.unsqueeze(-1)) ** 2).mean(-1) / (h * math.sqrt(2 * math.pi))
        factor = 1.0 / (4 * f0 * f0)
    return factor[..., None, None] * P, sigma2, factor


def _remaining_step(
    J: torch.Tensor, r: torch.Tensor, loss: _Loss, factor: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The undamped step ``d = -H^+ g`` of the iteration's quadratic model at the estimate
    (``H = J'CJ``, ``g = J' psi(r)``, see :func:`_levenberg_marquardt`) and its length in
    standard errors ``z = sqrt(d' Cov^{-1} d) = ||J d|| / sqrt(factor)`` for the covariance
    ``factor (J'J)^{-1}`` of :func:`_covariance`. Returns ``d`` ``(*batch, p)`` and ``z``
    ``(*batch,)``; the pseudo-inverse leaves unidentifiable directions (``H`` singular) out."""
    Jt = J.transpose(-1, -2)
    H = Jt @ (J * loss.curvature(r).unsqueeze(-1))
    g = Jt @ loss.psi(r).unsqueeze(-1)
    d = -(torch.linalg.pinv(H, hermitian=True) @ g)
    z = (J @ d).squeeze(-1).norm(dim=-1) / factor.sqrt()
    return d.squeeze(-1), z


# ---------------------------------------------------------------------------- data plumbing
def _with_outputs(data: IOData, y: torch.Tensor) -> IOData:
    """Same inputs and experiment split as ``data`` but outputs ``y`` (``(*batch, N, 1)``)."""
    if data.n_experiments == 1:
        return IOData(data.u, y, data.Ts)
    parts, start = [], 0
    for part in data.experiment_list:
        parts.append(IOData(part.u, y[..., start : start + part.N, :], data.Ts))
        start += part.N
    return IOData.experiments(parts)


def _regression_rows(data: IOData, M: int) -> list[slice]:
    """Slices of the concatenated samples used by a regression with ``M`` rows in all."""
    skip = (data.N - M) // data.n_experiments
    rows, start = [], 0
    for part in data.experiment_list:
        rows.append(slice(start + skip, start + part.N))
        start += part.N
    return rows


def _weights(weights, data: IOData) -> torch.Tensor | None:
    if weights is None:
        return None
    w = torch.as_tensor(weights, dtype=data.dtype, device=data.device)
    if w.dim() >= 2 and w.shape[-1] == 1 and w.shape[-2] == data.N:
        w = w[..., 0]
    if w.shape[-1] != data.N:
        raise InputValidationError(
            f"weights must have shape (*batch, N) with N = {data.N} samples; got {tuple(w.shape)}."
        )
    if bool((~torch.isfinite(w) | (w <= 0)).any()):
        raise InputValidationError("weights must be finite and positive (1 / noise variance).")
    _check_broadcast("weights", w, (*data.batch_shape, data.N), "(*batch, N) or (N,)")
    return w.expand(*data.batch_shape, data.N)


def _check_broadcast(name: str, x: torch.Tensor, shape: tuple, expected: str) -> None:
    """Raise unless ``x`` broadcasts to ``shape`` (the data's batch shape and one more size)."""
    try:
        torch.broadcast_shapes(x.shape, shape)
        ok = x.dim() <= len(shape) and torch.broadcast_shapes(x.shape, shape) == shape
    except RuntimeError:
        ok = False
    if not ok:
        raise InputValidationError(
            f"{name} has shape {tuple(x.shape)}, which does not broadcast to {tuple(shape)}: "
            f"it must be {expected} for data of batch shape {tuple(shape[:-1])}."
        )


# ---------------------------------------------------------------------------- initial values
def _aux_arx(model: PolynomialModel, na: int, nb, nk, batch) -> ARX:
    """An auxiliary ARX model (``nb = 0`` allowed: an AR model of a residual)."""
    return ARX(
        na,
        nb,
        nk,
        n_inputs=model.n_inputs,
        batch_shape=batch,
        dtype=model.a.dtype,
        device=model.a.device,
        Ts=model.Ts,
    )


def _stable_denominator(b_parts: list[torch.Tensor], a: torch.Tensor, model, batch) -> torch.Tensor:
    """``a`` with roots outside the unit circle reflected inside (via an output-error model)."""
    na = a.shape[-1]
    if na == 0:
        return a
    oe = PolynomialModel(
        nb=[bp.shape[-1] for bp in b_parts],
        nf=[na] * len(b_parts),
        nk=model.nk,
        n_inputs=model.n_inputs,
        batch_shape=batch,
        dtype=a.dtype,
        device=a.device,
    )
    oe.set_parameter_vector(torch.cat([*b_parts, *([a] * len(b_parts))], dim=-1))
    oe.stabilize()
    return oe.parameter_vector()[..., -na:].detach()


def _instrumental_variables(aux: PolynomialModel, data: IOData, n_iter: int = 2):
    """ARX estimate by instrumental variables; returns ``(theta, Z, Phi, target)``.

    Start: least squares. Then ``n_iter`` times: simulate the noise-free output ``x = B/A u``
    of the current (stabilised) estimate, build the instruments ``Z`` = the ARX regressors with
    ``x`` in place of ``y``, and solve ``(Z'Phi) theta = Z' target``.
    """
    Phi, target = aux.regression(data)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoorExcitationWarning)
        theta = lls(Phi, target).theta
    if aux.na == 0:
        return theta, Phi, Phi, target
    batch = theta.shape[:-1]
    na = aux.na
    Z = Phi
    for _ in range(n_iter):
        b_parts = list(torch.split(theta[..., na:], aux.nb, dim=-1))
        a = _stable_denominator(b_parts, theta[..., :na], aux, batch)
        x = aux.simulate(data, theta=torch.cat([a, theta[..., na:]], dim=-1))
        Z, _ = aux.regression(_with_outputs(data, x))
        ZtPhi = Z.transpose(-1, -2) @ Phi
        sol, info = torch.linalg.solve_ex(ZtPhi, (Z.transpose(-1, -2) @ target.unsqueeze(-1)))
        if bool((info != 0).any()):
            idx = tuple(int(i) for i in torch.nonzero(info)[0])
            raise SingularMatrixError(
                f"instrumental variables: Z'Phi is singular at batch index {idx}; the input "
                "does not excite the model (or the orders are too high)."
            )
        theta = sol.squeeze(-1)
    return theta, Z, Phi, target


def _initial_estimate(model: PolynomialModel, data: IOData) -> torch.Tensor:
    """A stable, consistent-ish starting point (never zero for OE/BJ/ARMAX).

    ARX/FIR: least squares. OE and the G-part of BJ: an ARX model with ``na = nf`` fitted by
    instrumental variables (``F = A``). ARMAX: A, B by instrumental variables, ``C = 1``.
    BJ: then ``D`` from an AR(nd) least-squares fit to the residual ``y - B/F u``, ``C = 1``.
    Finally roots of C, D, F outside the unit circle are reflected inside.
    """
    batch = data.batch_shape
    g = _groups(model)
    theta0 = torch.zeros(*batch, model.n_params, dtype=data.dtype, device=data.device)
    has_f = any(len(ix) for ix in g["f"])
    if model.na and has_f:
        return model.parameter_vector().detach().expand(*batch, model.n_params).clone()
    if model.is_linear_in_parameters:
        Phi, target = model.regression(data)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PoorExcitationWarning)
            return lls(Phi, target).theta
    nb = [len(ix) for ix in g["b"]]
    if not any(nb):
        return theta0
    na_aux = model.na if model.na else max(model.nf)
    aux = _aux_arx(model, na_aux, nb, model.nk, batch)
    th_aux, *_ = _instrumental_variables(aux, data)
    a_aux, b_aux = th_aux[..., :na_aux], th_aux[..., na_aux:]
    if model.na:
        theta0[..., g["a"][0]] = a_aux
    for ix, bpart in zip(g["b"], torch.split(b_aux, nb, dim=-1), strict=True):
        theta0[..., ix] = bpart
    for ix in g["f"]:
        theta0[..., ix] = a_aux[..., : len(ix)]
    if g["d"] and len(g["d"][0]):
        nd = len(g["d"][0])
        v = data.y - model.simulate(data, theta=theta0)
        ar = _aux_arx(model, nd, 0, 0, batch)
        ar_data = _with_outputs(data, v)
        Phi, target = ar.regression(ar_data)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PoorExcitationWarning)
            theta0[..., g["d"][0]] = lls(Phi, target).theta[..., :nd]
    holder = _copy_model(model, batch)
    holder.set_parameter_vector(theta0)
    holder.stabilize()
    return holder.parameter_vector().detach()


def _copy_model(model: PolynomialModel, batch) -> PolynomialModel:
    new = PolynomialModel(
        model.na,
        model.nb,
        model.nc,
        model.nd,
        model.nf,
        model.nk,
        n_inputs=model.n_inputs,
        batch_shape=batch,
        dtype=model.a.dtype,
        device=model.a.device,
        Ts=model.Ts,
    )
    new.__class__ = model.__class__
    return new


# ---------------------------------------------------------------------------- fit
def _admissible_fn(model: PolynomialModel, criterion: str):
    """Candidates must give a stable predictor: roots of C and F_i (prediction errors,
    eq. 4.132 divides by C F) or of A and F_i (simulation errors) inside the unit circle."""
    g = _groups(model)
    letters = ("c", "f") if criterion == "prediction" else ("a", "f")
    blocks = [ix for letter in letters for ix in g[letter] if len(ix)]
    if not blocks:
        return None
    return lambda th: _max_root_modulus(th, blocks) < 1.0


def fit(
    model: PolynomialModel,
    data: IOData,
    method: str | None = None,
    loss: str = "gaussian",
    *,
    alpha: float | None = None,
    weights=None,
    criterion: str = "prediction",
    init=None,
    max_iter: int = 100,
    xtol: float = 1e-8,
    ftol: float = 1e-10,
    iv_iterations: int = 2,
) -> FitResult:
    """Estimate the parameters of ``model`` from ``data`` (batched over data sets).

    Args:
        model: FIR, ARX, OE, ARMAX, BJ or a general :class:`PolynomialModel`. Its batch shape
            must equal the data's, or be empty (a batched copy is then fitted and returned in
            ``result.model``); otherwise the model is updated in place.
        data: :class:`IOData` (one output), ``(*batch, N, nu)`` / ``(*batch, N, 1)``.
        method: ``"lls"`` (FIR/ARX, eq. 4.111–4.112), ``"iv"`` (ARX structure),
            ``"gauss_newton"`` (Levenberg–Marquardt on prediction errors) or ``"mle"`` (with
            ``loss``). Default: ``"lls"`` for FIR/ARX, ``"gauss_newton"`` otherwise, and
            ``"mle"`` whenever ``loss`` is not Gaussian.
        loss: noise model of ``"mle"``: ``"gaussian"`` (weighted LS, eq. 4.64), ``"fair"``
            (eq. 4.73) or ``"laplace"``.
        alpha: the fair loss' ``alpha`` (1/output units); default ``1 / s`` with ``s`` a
            robust (MAD) scale of the least-squares residuals.
        weights: per-sample weights ``1/sigma_k^2`` of the Gaussian loss, ``(*batch, N)``.
        criterion: ``"prediction"`` (one-step prediction errors, eq. 4.130; the simulation
            error for OE) or ``"simulation"`` (free-run errors for any structure).
        init: starting parameters ``(*batch, p)``, ``"model"`` (the model's current values) or
            ``None`` (automatic: ARX least squares / instrumental variables, stabilised).
        max_iter, xtol, ftol: iteration limit and step/relative-decrease tolerances.
        iv_iterations: instrument refinements of ``"iv"`` (and of the automatic start).

    Returns:
        :class:`FitResult` (the model's parameters are set to the estimate).
    """
    if not isinstance(model, PolynomialModel):
        raise InputValidationError(f"model must be a sysid model, got {type(model).__name__}.")
    if not isinstance(data, IOData):
        raise InputValidationError(f"data must be IOData, got {type(data).__name__}.")
    if loss not in LOSSES:
        raise InputValidationError(f"loss must be one of {LOSSES}, got {loss!r}.")
    if criterion not in ("prediction", "simulation"):
        raise InputValidationError(
            f"criterion must be 'prediction' or 'simulation', got {criterion!r}."
        )
    if alpha is not None:
        _check_alpha(alpha)
    linear = model.is_linear_in_parameters and criterion == "prediction"
    if method is None:
        method = "mle" if loss != "gaussian" else ("lls" if linear else "gauss_newton")
    if method not in METHODS:
        raise InputValidationError(f"method must be one of {METHODS}, got {method!r}.")
    if method in ("lls", "iv", "gauss_newton") and loss != "gaussian":
        raise InputValidationError(
            f"method {method!r} minimises squared errors; use method='mle' for loss={loss!r}."
        )
    if method in ("lls", "iv") and not model.is_linear_in_parameters:
        raise InputValidationError(
            f"method {method!r} needs a model linear in its parameters (FIR, ARX); "
            f"{type(model).__name__} is not: use method='gauss_newton'."
        )
    data = model._check_data(data)  # one output, matching number of inputs
    if data.dtype != model.a.dtype:
        data = data.to(dtype=model.a.dtype)
    batch = data.batch_shape
    model = _batched_model(model, batch)
    w = _weights(weights, data)
    names = model.parameter_names()

    if method == "lls" or (method == "mle" and linear and loss == "gaussian"):
        result = _fit_lls(model, data, w, method)
    elif method == "iv":
        result = _fit_iv(model, data, iv_iterations)
    else:
        result = _fit_iterative(
            model, data, method, loss, alpha, w, criterion, init, linear, max_iter, xtol, ftol
        )
    result.parameter_names = names
    model.set_parameter_vector(result.theta)
    result.model = model
    _diagnose(result, model)
    return result


def _diagnose(result: FitResult, model: PolynomialModel) -> None:
    """Set ``result.stable`` and ``result.messages``; warn about the data sets whose estimate
    did not converge (:class:`ConvergenceWarning`) or is unstable
    (:class:`UnstableModelWarning`)."""
    poles = model.poles()
    modulus = poles.abs().amax(dim=-1) if poles.shape[-1] else torch.zeros(model.batch_shape)
    modulus = modulus.to(result.theta.device)
    result.info["max_pole_modulus"] = modulus
    result.stable = modulus < 1
    info = result.info
    not_converged, unstable = [], []
    for idx in _indices(~result.converged):  # only the data sets with a problem
        m = float(modulus[idx])
        if bool(info["line_search_failed"][idx]):
            why = "the line search found no decrease (damping grew past 1e10)"
        elif bool(info["iteration_limit_reached"][idx]):
            why = f"the iteration limit max_iter = {info['max_iter']} was reached"
        else:
            why = "the iteration stopped away from a stationary point"
        why += (
            f"; a Newton step from the estimate would still move it by "
            f"{float(info['step_in_standard_errors'][idx]):.3g} standard errors "
            f"(converged means <= {STATIONARY_TOL})"
        )
        if bool(info["stationary_point_unstable"][idx]) or m > _BOUNDARY_MODULUS:
            why += (
                f". That step would leave the stable models (the estimate's largest pole "
                f"modulus is {m:.4g}): the data look like the response of an unstable "
                "system, which a model simulated in free run (output error) cannot follow; "
                "fit an ARX or "
                "ARMAX model (their predictors are stable for any A) or use closed-loop data"
            )
        else:
            why += "; raise max_iter, start closer (init=...), or use float64"
        not_converged.append(f"batch index {idx}: did not converge: {why}.")
    for idx in _indices(~result.stable):
        unstable.append(
            f"batch index {idx}: the estimated model is unstable (largest pole modulus "
            f"{float(modulus[idx]):.6g} >= 1): its free-run simulation diverges, so "
            "simulation errors and fit percentages are meaningless; the data may come from an "
            "unstable system (or a closed loop): use one-step predictions, not simulations."
        )
    result.messages = not_converged + unstable
    for lines, category, what in (
        (not_converged, ConvergenceWarning, "did not converge"),
        (unstable, UnstableModelWarning, "gave an unstable model"),
    ):
        if lines:
            shown = "\n  ".join(lines[:5])
            more = f"\n  ... and {len(lines) - 5} more" if len(lines) > 5 else ""
            warnings.warn(
                f"fit: {len(lines)} of {result.converged.numel()} data sets {what}:"
                f"\n  {shown}{more}\n(result.messages lists them all; result.converged and "
                "result.stable flag them.)",
                category,
                stacklevel=3,
            )


def _indices(mask: torch.Tensor) -> list[tuple[int, ...]]:
    """Batch multi-indices of the True entries of ``mask`` (``()`` for an unbatched one)."""
    return [tuple(int(i) for i in row) for row in torch.nonzero(mask).tolist()]


def _check_alpha(alpha) -> None:
    """Raise unless the fair loss' ``alpha`` is finite and > 0 (scalar or per data set)."""
    a = torch.as_tensor(alpha, dtype=torch.float64)
    if not bool((torch.isfinite(a) & (a > 0)).all()):
        bad = a.reshape(-1)[~(torch.isfinite(a) & (a > 0)).reshape(-1)][0].item()
        raise InputValidationError(
            f"alpha of the fair loss must be finite and > 0, got {bad}. alpha (1/output units) "
            "sets where rho(r) = r^2 / (2 (1 + alpha |r|)) (eq. 4.73) turns from quadratic to "
            "linear: at |r| ~ 1/alpha. alpha <= 0 makes the loss non-convex and its standard "
            "errors wrong. A typical value is 1/sigma with sigma the noise standard deviation; "
            "alpha=None uses 1/s with s a robust (MAD) scale of the least-squares residuals."
        )


def _fit_lls(model, data, w, method) -> FitResult:
    Phi, target = model.regression(data)
    W = None
    if w is not None:
        W = torch.cat([w[..., sl] for sl in _regression_rows(data, target.shape[-1])], dim=-1)
    res = lls(Phi, target, W=W)
    batch = res.theta.shape[:-1]
    f = 0.5 * (res.residuals**2 * (1 if W is None else W)).sum(-1)
    return FitResult(
        theta=res.theta,
        covariance=res.covariance,
        standard_errors=res.standard_errors,
        sigma2=res.sigma2,
        loss_history=f.unsqueeze(0),
        iterations=torch.zeros(batch, dtype=torch.int64, device=f.device),
        converged=torch.ones(batch, dtype=torch.bool, device=f.device),
        method=method,
        loss="gaussian",
        parameter_names=[],
        n_samples=target.shape[-1],
        residuals=res.residuals,
        info={
            "condition_number": res.condition_number,
            "scaled_condition_number": res.scaled_condition_number,
        },
    )


def _fit_iv(model, data, iv_iterations) -> FitResult:
    theta, Z, Phi, target = _instrumental_variables(model, data, max(1, iv_iterations))
    r = target - (Phi @ theta.unsqueeze(-1)).squeeze(-1)
    M, p = Phi.shape[-2], Phi.shape[-1]
    sigma2 = (r * r).sum(-1) / (M - p)
    ZtPhi = Z.transpose(-1, -2) @ Phi
    # (Z'Phi)^{-1} Z'Z (Z'Phi)^{-T} by two solves
    left = torch.linalg.solve(ZtPhi, Z.transpose(-1, -2) @ Z)
    cov = sigma2[..., None, None] * torch.linalg.solve(ZtPhi, left.transpose(-1, -2))
    cov = 0.5 * (cov + cov.transpose(-1, -2))
    batch = theta.shape[:-1]
    return FitResult(
        theta=theta,
        covariance=cov,
        standard_errors=torch.diagonal(cov, dim1=-2, dim2=-1).clamp_min(0).sqrt(),
        sigma2=sigma2,
        loss_history=(0.5 * (r * r).sum(-1)).unsqueeze(0),
        iterations=torch.full(batch, max(1, iv_iterations), dtype=torch.int64, device=r.device),
        converged=torch.ones(batch, dtype=torch.bool, device=r.device),
        method="iv",
        loss="gaussian",
        parameter_names=[],
        n_samples=M,
        residuals=r,
    )


def _fit_iterative(
    model, data, method, loss, alpha, w, criterion, init, linear, max_iter, xtol, ftol
) -> FitResult:
    batch = data.batch_shape
    p = model.n_params
    sw = None if w is None else w.sqrt()
    if linear:
        Phi, target = model.regression(data)
        if sw is not None:
            rows = _regression_rows(data, target.shape[-1])
            swr = torch.cat([sw[..., sl] for sl in rows], dim=-1)
            Phi, target = Phi * swr.unsqueeze(-1), target * swr

        def residual_fn(th):
            return target - (Phi @ th.unsqueeze(-1)).squeeze(-1)

        def jacobian_fn(th):
            return residual_fn(th), (-Phi).expand(*th.shape[:-1], *Phi.shape[-2:])

        admissible = None
    else:
        errors = model.prediction_errors if criterion == "prediction" else model.simulation_errors

        def residual_fn(th):
            e = errors(data, theta=th)[..., 0]
            return e if sw is None else e * sw

        jacobian_fn = None
        if model.na == model.nc == model.nd == 0:  # H = 1: prediction errors = simulation errors
            output_error = _OutputError(model, data, sw)
            residual_fn, jacobian_fn = output_error.residuals, output_error.linearise
        admissible = _admissible_fn(model, criterion)

    if init is None and linear:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PoorExcitationWarning)
            theta0 = lls(Phi, target).theta
    elif init is None:
        theta0 = _initial_estimate(model, data)
    elif isinstance(init, str) and init == "model":
        theta0 = model.parameter_vector().detach().expand(*batch, p).clone()
    else:
        theta0 = torch.as_tensor(init, dtype=data.dtype, device=data.device)
        _check_broadcast("init", theta0, (*batch, p), "(*batch, p) or (p,)")
        theta0 = theta0.expand(*batch, p).clone()
    if admissible is not None and not bool(admissible(theta0).all()):
        idx = tuple(int(i) for i in torch.nonzero(~admissible(theta0))[0])
        raise InputValidationError(
            f"the initial model gives an unstable predictor at batch index {idx}; start from a "
            "stable model (e.g. init=None for the automatic start)."
        )
    kwargs = dict(max_iter=max_iter, xtol=xtol, ftol=ftol, admissible=admissible)
    gauss = _Loss("gaussian")
    lm = _levenberg_marquardt(residual_fn, theta0, gauss, jacobian_fn=jacobian_fn, **kwargs)
    history, iterations = lm.history, lm.iterations
    the_loss = gauss
    if loss != "gaussian":
        scale = _robust_scale(lm.residuals).clamp_min(torch.finfo(data.dtype).tiny)
        if loss == "fair":
            a = (1.0 / scale) if alpha is None else torch.as_tensor(alpha, dtype=data.dtype)
            the_loss = _Loss(
                "fair", alpha=torch.as_tensor(a).unsqueeze(-1) if torch.as_tensor(a).dim() else a
            )
        else:
            the_loss = _Loss("laplace", eps=(1e-4 * scale).unsqueeze(-1))
        lm = _levenberg_marquardt(
            residual_fn,
            lm.theta,
            the_loss,
            jacobian_fn=jacobian_fn,
            **{**kwargs, "max_iter": max(max_iter, 500) if loss == "laplace" else max_iter},
        )
        history = lm.history
        iterations = iterations + lm.iterations
    cov, sigma2, factor = _covariance(lm.jacobian, lm.residuals, the_loss)
    # converged: at a stationary point to within STATIONARY_TOL standard errors (or, for
    # noise-free data where the standard errors vanish, to within sqrt(eps) relative)
    d, z = _remaining_step(lm.jacobian, lm.residuals, the_loss, factor)
    tiny_step = d.norm(dim=-1) <= math.sqrt(torch.finfo(d.dtype).eps) * (1 + lm.theta.norm(dim=-1))
    converged = (z <= STATIONARY_TOL) | tiny_step
    # where the step to the stationary point would leave the stable models, the optimum of
    # the criterion lies beyond the stability boundary (e.g. an unstable plant)
    beyond = torch.zeros_like(converged) if admissible is None else ~admissible(lm.theta + d)
    return FitResult(
        theta=lm.theta,
        covariance=cov,
        standard_errors=torch.diagonal(cov, dim1=-2, dim2=-1).clamp_min(0).sqrt(),
        sigma2=sigma2,
        loss_history=history,
        iterations=iterations,
        converged=converged,
        method=method,
        loss=loss,
        parameter_names=[],
        n_samples=lm.residuals.shape[-1],
        residuals=lm.residuals,
        info={
            "damping": lm.damping,
            "initial_theta": theta0,
            "step_in_standard_errors": z,
            "line_search_failed": lm.failed,
            "stationary_point_unstable": beyond,
            "iteration_limit_reached": ~(lm.converged | lm.failed),
            "max_iter": max_iter,
        },
    )


# ---------------------------------------------------------------------------- uniform noise
@dataclass
class UniformNoiseSet:
    """The maximum-likelihood set ``{theta : |y - A theta| <= a}`` (eq. 4.58) of a linear model.

    Attributes:
        A, y, a: the problem (``(*batch, M, p)``, ``(*batch, M)``, noise bound).
        lower, upper: per-parameter bounds of the polytope, ``(*batch, p)`` (``+-inf`` where
            unbounded, ``nan`` only for an empty set).
        feasible: whether the set is non-empty, ``(*batch,)`` bool (empty: every theta has
            likelihood 0, so every theta is an MLE, eq. 4.58 remark).
        center: Chebyshev centre (centre of the largest inscribed ball), ``(*batch, p)``.
        radius: radius of that ball, ``(*batch,)``.
    """

    A: torch.Tensor
    y: torch.Tensor
    a: float
    lower: torch.Tensor
    upper: torch.Tensor
    feasible: torch.Tensor
    center: torch.Tensor
    radius: torch.Tensor

    def contains(self, theta: torch.Tensor, tol: float = 1e-9) -> torch.Tensor:
        """Whether ``theta`` (``(*batch, p)``) lies in the set (``(*batch,)`` bool)."""
        theta = torch.as_tensor(theta, dtype=self.A.dtype, device=self.A.device)
        r = self.y - (self.A @ theta.unsqueeze(-1)).squeeze(-1)
        return (r.abs() <= self.a * (1 + tol) + tol).all(dim=-1)


def uniform_noise_mle_set(A: torch.Tensor, y: torch.Tensor, a: float) -> UniformNoiseSet:
    """Set of maximum-likelihood estimates for ``y = A theta + e``, ``e ~ U[-a, a]`` i.i.d.

    The likelihood (eq. 4.44–4.45, scaled to ``[-a, a]``) is ``(2a)^-M`` where every residual
    satisfies ``|y_k - A_k theta| <= a`` and 0 elsewhere, so its maximisers form the polytope
    ``{theta : -a <= y - A theta <= a}`` (eq. 4.58). Each bound ``min/max theta_j`` over the
    polytope is one linear program (scipy HiGHS); the Chebyshev centre is one more.

    Args:
        A: ``(*batch, M, p)`` regressors; y: ``(*batch, M)``; a: noise half-width (> 0).

    Returns:
        :class:`UniformNoiseSet`.
    """
    if not a > 0:
        raise InputValidationError(f"the noise half-width a must be > 0, got {a}.")
    A = torch.as_tensor(A)
    y = torch.as_tensor(y, dtype=A.dtype, device=A.device)
    if A.dim() < 2 or y.shape[-1] != A.shape[-2]:
        raise InputValidationError(
            f"A must be (*batch, M, p) and y (*batch, M); got {tuple(A.shape)}, {tuple(y.shape)}."
        )
    batch = torch.broadcast_shapes(A.shape[:-2], y.shape[:-1])
    M, p = A.shape[-2:]
    An = A.expand(*batch, M, p).detach().cpu().double().numpy().reshape(-1, M, p)
    yn = y.expand(*batch, M).detach().cpu().double().numpy().reshape(-1, M)
    lower = np.full((len(An), p), np.nan)
    upper = np.full((len(An), p), np.nan)
    center = np.full((len(An), p), np.nan)
    radius = np.full(len(An), np.nan)
    feasible = np.zeros(len(An), dtype=bool)
    free = [(None, None)] * p
    for b in range(len(An)):  # one small LP per data set and bound (scipy has no batch)
        G = np.vstack([An[b], -An[b]])
        h = np.concatenate([yn[b] + a, a - yn[b]])
        norms = np.linalg.norm(G, axis=1, keepdims=True)
        cheb = scipy.optimize.linprog(
            np.r_[np.zeros(p), -1.0],
            A_ub=np.hstack([G, norms]),
            b_ub=h,
            bounds=free + [(0, None)],
            method="highs",
        )
        if cheb.status == 2:  # infeasible
            continue
        feasible[b] = True
        if cheb.status == 0:
            center[b], radius[b] = cheb.x[:p], cheb.x[p]
        else:
            radius[b] = np.inf
        for j in range(p):
            for sign, store in ((1.0, lower), (-1.0, upper)):
                c = np.zeros(p)
                c[j] = sign
                res = scipy.optimize.linprog(c, A_ub=G, b_ub=h, bounds=free, method="highs")
                if res.status == 3:
                    store[b, j] = -sign * np.inf
                else:
                    store[b, j] = res.x[j]
    to = dict(dtype=A.dtype, device=A.device)
    return UniformNoiseSet(
        A=A,
        y=y,
        a=float(a),
        lower=torch.as_tensor(lower, **to).reshape(*batch, p),
        upper=torch.as_tensor(upper, **to).reshape(*batch, p),
        feasible=torch.as_tensor(feasible, device=A.device).reshape(batch),
        center=torch.as_tensor(center, **to).reshape(*batch, p),
        radius=torch.as_tensor(radius, **to).reshape(batch),
    )
