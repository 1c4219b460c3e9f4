"""Batched weighted linear least squares with covariance (notes §4.4–4.5).

Solves ``theta = argmin 1/2 ||y - A theta||_W^2``, whose normal equations give
``theta = (A'WA)^{-1} A'W y`` (eq. 4.81), for a whole batch of data sets at once. The solve
uses a QR factorisation of the row-scaled regressor ``W^{1/2} A`` (default) or a Cholesky
factorisation of the column-equilibrated normal matrix; no inverse is ever formed.

Covariance of the estimate (notes §4.5):

* noise covariance ``Sigma`` given: the sandwich ``(A'WA)^{-1} A'W Sigma W A (A'WA)^{-1}``
  (eq. 4.92), which reduces to ``(A' Sigma^{-1} A)^{-1}`` when ``W = Sigma^{-1}`` (eq. 4.93)
  and to ``sigma^2 (U'U)^{-1}`` for white noise and ``W = I`` (eq. 4.101);
* ``Sigma`` not given: the weights are taken as known up to a common scale,
  ``Sigma = sigma^2 W^{-1}``, and ``sigma^2`` is estimated from the weighted residuals,
  ``sigma2_hat = r'Wr / (M - p)``, giving ``sigma2_hat (A'WA)^{-1}`` (the convention of
  statsmodels' OLS/WLS).
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from integrators.errors import InputValidationError, SingularMatrixError

from .errors import PoorExcitationWarning
from .filters import fir_filter

__all__ = [
    "DEFAULT_COND_WARN",
    "NORMAL_EQUATIONS_ROUNDING",
    "ROUNDING_WARN",
    "LLSResult",
    "accurate_normal_equations",
    "fir_lls",
    "lls",
]

#: Condition number of the column-scaled ``A'WA`` above which :func:`lls` warns of poor
#: excitation. At 1e4 the standard deviation of the estimate in the worst excited direction is
#: 100 times larger than in the best one (for unit-norm regressors): e.g. a sinusoid or a step
#: driving a 20-tap FIR model (notes Fig. 4.1; both are persistently exciting of order 2 and 1
#: only, so the condition number grows with the number of samples), or two regressors with a
#: correlation above 0.9998. White noise and PRBS give condition numbers of a few units.
DEFAULT_COND_WARN = 1e4

#: :func:`lls` also warns, whatever ``cond_warn``, where the first-order bound on the relative
#: rounding error of the estimate exceeds ``ROUNDING_WARN`` (fewer than two correct digits).
#: With ``kappa = sqrt(cond)`` (the scaled condition number of ``W^{1/2} A``) the bound is
#: ``eps kappa^2`` for the normal equations (``method="cholesky"``, :func:`fir_lls`) and
#: ``eps (kappa + kappa^2 tan(phi))`` for QR, ``tan(phi) = ||r|| / ||A theta||`` (Golub & Van
#: Loan, Matrix Computations, Thm. 5.3.1); ``eps`` is the dtype's: 1.2e-7 in float32,
#: 2.2e-16 in float64.
ROUNDING_WARN = 1e-2

#: :func:`accurate_normal_equations` (the normal-equation route of ``sysid.fit(...,
#: method="lls")``) is used only where the rounding-error bound ``eps cond`` of the
#: normal equations is at most this (at least 10 correct digits; in float64 a scaled condition
#: number up to 4.5e5, white-noise and PRBS regressors have a few units to a few hundred);
#: elsewhere, and always in float32, the estimate comes from :func:`lls`'s QR factorisation.
NORMAL_EQUATIONS_ROUNDING = 1e-10


@dataclass
class LLSResult:
    """Result of :func:`lls` for a batch of problems.

    Attributes:
        theta: estimate, shape ``(*batch, p)``.
        covariance: covariance of the estimate, ``(*batch, p, p)`` (eq. 4.92/4.93, or
            ``sigma2 (A'WA)^{-1}`` when no noise covariance was given).
        standard_errors: square roots of the diagonal of ``covariance``, ``(*batch, p)``.
        sigma2: residual variance ``r'Wr / (M - p)``, ``(*batch,)`` (always computed; it is the
            noise variance estimate when ``W`` is the identity).
        residuals: ``y - A theta``, ``(*batch, M)``.
        condition_number: 2-norm condition number of ``A'WA``, ``(*batch,)`` (with
            ``method="cholesky"`` and in :func:`fir_lls` a power-iteration estimate, see
            ``_condition_estimate``).
        scaled_condition_number: condition number of ``D A'WA D`` with ``D`` scaling the
            columns of ``W^{1/2} A`` to unit norm (insensitive to the units of the regressors;
            it drives the warning and the singularity test), ``(*batch,)``. With
            ``method="cholesky"`` and in :func:`fir_lls` a power-iteration estimate, which
            the warning and the singularity test need only where a cheap upper bound reaches
            their thresholds (see ``_screened_condition``).
        dof: residual degrees of freedom ``M - p`` (``M``: the rows with a positive weight;
            an int, or ``(*batch,)`` where diagonal weights with zeros give the problems
            different counts).
        normal_inverse: ``(A'WA)^{-1}``, ``(*batch, p, p)``.
        singular: ``(*batch,)`` bool: the problems whose ``A'WA`` is numerically singular
            (all False unless ``singular="nan"``); their estimate, standard errors, ``sigma2``,
            covariance, normal inverse and residuals are NaN and their condition numbers inf.

    ``covariance``, ``residuals``, ``condition_number``, ``scaled_condition_number`` and
    ``normal_inverse`` are properties: where the solver deferred them (:func:`fir_lls`;
    the condition numbers also with ``method="cholesky"``) they are computed on first read.
    """

    theta: torch.Tensor
    standard_errors: torch.Tensor
    sigma2: torch.Tensor
    dof: int | torch.Tensor
    singular: torch.Tensor
    _covariance: torch.Tensor | Callable[[], torch.Tensor] = field(repr=False)
    _normal_inverse: torch.Tensor | Callable[[], torch.Tensor] = field(repr=False)
    _scaled_condition_number: torch.Tensor | Callable[[], torch.Tensor] = field(repr=False)
    _residuals: torch.Tensor | Callable[[], torch.Tensor] = field(repr=False)
    _condition_number: torch.Tensor | Callable[[], torch.Tensor] = field(repr=False)

    def _resolve(self, name: str) -> torch.Tensor:
        """The tensor stored as ``name``, computing (and keeping) a deferred one first."""
        value = getattr(self, name)
        if not isinstance(value, torch.Tensor):
            value = value()
            setattr(self, name, value)
        return value

    @property
    def covariance(self) -> torch.Tensor:
        """Covariance of the estimate, ``(*batch, p, p)``."""
        return self._resolve("_covariance")

    @property
    def normal_inverse(self) -> torch.Tensor:
        """``(A'WA)^{-1}``, ``(*batch, p, p)``."""
        return self._resolve("_normal_inverse")

    @property
    def residuals(self) -> torch.Tensor:
        """``y - A theta``, ``(*batch, M)``."""
        return self._resolve("_residuals")

    @property
    def condition_number(self) -> torch.Tensor:
        """2-norm condition number of ``A'WA``, ``(*batch,)``."""
        return self._resolve("_condition_number")

    @property
    def scaled_condition_number(self) -> torch.Tensor:
        """Condition number of the column-scaled ``A'WA``, ``(*batch,)``."""
        return self._resolve("_scaled_condition_number")


def _first_index(mask: torch.Tensor) -> tuple[int, ...]:
    """Multi-index of the first True entry of a boolean tensor (shape ``batch``)."""
    flat = int(torch.nonzero(mask.reshape(-1))[0, 0])
    if mask.dim() == 0:
        return ()
    return tuple(int(i) for i in torch.unravel_index(torch.tensor(flat), mask.shape))


def _check_real(name: str, x) -> None:
    """Raise for complex data: least squares here is over the reals, and a cast would drop
    the imaginary parts."""
    if (isinstance(x, torch.Tensor) and x.is_complex()) or (
        not isinstance(x, torch.Tensor) and torch.as_tensor(x).is_complex()
    ):
        raise InputValidationError(
            f"{name} is complex; least squares here is over the reals. Stack the real and "
            "imaginary parts as separate rows (A -> [Re A; Im A], y -> [Re y; Im y]) for a "
            "real parameter vector."
        )


def _check_finite(name: str, x: torch.Tensor, where: str = "lls") -> None:
    if bool(torch.isfinite(x.sum())):  # one cheap reduction; locate only on failure
        return
    bad = ~torch.isfinite(x)
    if bool(bad.any()):
        idx = _first_index(bad)
        raise InputValidationError(
            f"{where}: {name} contains a non-finite value at index {idx}; remove or impute the "
            "offending samples before fitting."
        )


def _batch_shape(where: str, x: torch.Tensor, x_name: str, x_core: int, y: torch.Tensor):
    """Broadcast batch shape of ``x`` (``x_core`` trailing non-batch dimensions) and ``y``
    (one trailing non-batch dimension); InputValidationError naming both shapes if none."""
    try:
        return torch.broadcast_shapes(x.shape[: x.dim() - x_core], y.shape[:-1])
    except RuntimeError:
        raise InputValidationError(
            f"{where}: the batch shapes of {x_name} {tuple(x.shape)} and y {tuple(y.shape)} do "
            "not broadcast; give them equal (or size-1) leading batch dimensions."
        ) from None


def _extra_batch(name: str, x, kind: str, batch: torch.Size, others: str) -> torch.Size:
    """The batch shape of ``A``, ``y`` (and ``W``) with ``x``'s (``W`` or ``sigma`` of the
    given kind) broadcast in; ``sigma`` may not widen it, as the estimate does not depend on
    it. InputValidationError naming the shapes otherwise."""
    if kind in ("none", "scalar"):
        return batch
    x_batch = x.shape[: x.dim() - (2 if kind == "full" else 1)]
    try:
        widened = torch.broadcast_shapes(batch, x_batch)
    except RuntimeError:
        widened = None
    if widened is None or (name == "sigma" and widened != batch):
        raise InputValidationError(
            f"lls: {name} has batch shape {tuple(x_batch)}, which does not broadcast to the "
            f"batch shape {tuple(batch)} of {others}; give {name} equal (or size-1) leading "
            "batch dimensions."
        )
    return widened


def _prepare_weights(W: torch.Tensor | None, M: int, like: torch.Tensor, y_dim: int):
    """Return ``(kind, W)`` with kind in {"none", "diag", "full"} after validation.

    A full weight matrix has one more dimension than ``y``; otherwise W is diagonal.
    """
    if W is None:
        return "none", None
    W = torch.as_tensor(W, dtype=like.dtype, device=like.device)
    _check_finite("W", W)
    if W.dim() > y_dim and W.dim() >= 2 and W.shape[-1] == M and W.shape[-2] == M:
        asym = (W - W.transpose(-1, -2)).abs().amax(dim=(-2, -1))
        if bool((asym > 1e-8 * W.abs().amax(dim=(-2, -1))).any()):
            raise InputValidationError("lls: the full weight matrix W must be symmetric.")
        return "full", 0.5 * (W + W.transpose(-1, -2))
    if W.dim() >= 1 and W.shape[-1] == M:
        if bool((W < 0).any()):
            idx = _first_index(W < 0)
            raise InputValidationError(
                f"lls: diagonal weights must be non-negative; W{list(idx)} < 0."
            )
        return "diag", W
    raise InputValidationError(
        f"lls: W must have shape (*batch, M) (diagonal weights) or (*batch, M, M) with one "
        f"more dimension than y; got {tuple(W.shape)} with M = {M}."
    )


def _prepare_sigma(sigma, M: int, like: torch.Tensor, y_dim: int):
    """Return ``(kind, Sigma)``, kind in {"none", "scalar", "diag", "full"} (full: one more
    dimension than ``y``)."""
    if sigma is None:
        return "none", None
    _check_real("lls: sigma", sigma)
    S = torch.as_tensor(sigma, dtype=like.dtype, device=like.device)
    if not bool(torch.isfinite(S).all()):
        idx = _first_index(~torch.isfinite(S))
        raise InputValidationError(
            f"lls: sigma (noise variance or covariance) is not finite at index {idx}; give "
            "finite variances > 0, or sigma=None to estimate the noise variance from the "
            "residuals."
        )
    if S.dim() == 0:
        kind, variances = "scalar", S
    elif S.dim() > y_dim and S.dim() >= 2 and S.shape[-1] == M and S.shape[-2] == M:
        asym = (S - S.transpose(-1, -2)).abs().amax(dim=(-2, -1))
        if bool((asym > 1e-8 * S.abs().amax(dim=(-2, -1))).any()):
            raise InputValidationError("lls: the full noise covariance sigma must be symmetric.")
        kind, variances = "full", torch.diagonal(S, dim1=-2, dim2=-1)
    elif S.shape[-1] == M:
        kind, variances = "diag", S
    else:
        kind = None
    if kind is not None:
        if bool((variances <= 0).any()):
            idx = _first_index(variances <= 0)
            raise InputValidationError(
                f"lls: sigma is the noise variance or covariance (sigma^2, not a standard "
                f"deviation), whose variances must be > 0; got {variances[idx].item()} at index "
                f"{idx}. Give variances > 0, or sigma=None to estimate the noise variance from "
                "the residuals."
            )
        return kind, S
    raise InputValidationError(
        f"lls: sigma (noise covariance) must be a scalar variance, (*batch, M) variances or a "
        f"(*batch, M, M) covariance; got {tuple(S.shape)} with M = {M}."
    )


def _degrees_of_freedom(wkind: str, W, M: int, p: int, batch: torch.Size):
    """Residual degrees of freedom ``M - p``, where ``M`` counts the rows with a positive
    weight (a row of weight 0 is not an observation): an int, or ``(*batch,)`` where diagonal
    weights give the problems different counts. Raises :class:`InputValidationError` where a
    problem has ``M <= p``."""
    if wkind != "diag":
        return M - p
    rows = (W > 0).sum(-1).expand(batch)
    if bool((rows <= p).any()):
        idx = _first_index(rows <= p)
        raise InputValidationError(
            f"lls: problem {idx} has {int(rows[idx])} rows with a positive weight for p = {p} "
            "parameters; a row of weight 0 is no equation: give more rows a positive weight or "
            "use a smaller model."
        )
    if bool((rows == rows.reshape(-1)[0]).all()):
        return int(rows.reshape(-1)[0]) - p
    return rows - p


def _cholesky_upper_of_weights(W: torch.Tensor) -> torch.Tensor:
    """``L'`` with ``W = L L'``, so that ``||x||_W^2 = ||L' x||^2``."""
    L, info = torch.linalg.cholesky_ex(W)
    if bool((info != 0).any()):
        idx = _first_index(info != 0)
        raise InputValidationError(
            f"lls: the weight matrix W at batch index {idx} is not positive definite."
        )
    return L.transpose(-1, -2)


def lls(
    A: torch.Tensor,
    y: torch.Tensor,
    W: torch.Tensor | None = None,
    sigma: torch.Tensor | float | None = None,
    *,
    method: str = "qr",
    cond_warn: float = DEFAULT_COND_WARN,
    singular: str = "raise",
) -> LLSResult:
    """Weighted linear least squares ``theta = (A'WA)^{-1} A'W y`` (eq. 4.81), batched.

    Args:
        A: regressor matrix, shape ``(*batch, M, p)``; its batch dimensions broadcast with
            those of ``y``, so one shared ``A`` (shape ``(M, p)``) and many ``y`` are factorised
            only once.
        y: measurements, shape ``(*batch, M)``.
        W: weights; ``None`` (identity), diagonal weights ``(*batch, M)`` (non-negative) or a
            symmetric positive definite ``(*batch, M, M)`` matrix. A full matrix must have
            one more dimension than ``y`` (expand a shared one to ``(*y.shape[:-1], M, M)``).
        sigma: noise covariance ``Sigma_e``; ``None`` (estimate ``sigma^2`` from the
            residuals and assume ``Sigma = sigma^2 W^{-1}``), a scalar variance
            (``sigma^2 I``), variances ``(*batch, M)`` or a full covariance
            ``(*batch, M, M)``. With ``sigma`` given the covariance is the sandwich of
            eq. 4.92.
        method: ``"qr"`` (QR of ``W^{1/2} A``; the default, most accurate) or ``"cholesky"``
            (Cholesky of the equilibrated normal matrix ``D A'WA D`` with
            ``D = diag(A'WA)^{-1/2}``; faster and lighter for very tall batches).
        cond_warn: warn with :class:`PoorExcitationWarning` when the column-scaled
            condition number of ``A'WA`` exceeds this (see :data:`DEFAULT_COND_WARN`), or
            ``ROUNDING_WARN / eps`` of the dtype if smaller (see :data:`ROUNDING_WARN`); the
            message gives the number of correct digits left, ``-log10(eps * cond)``.
        singular: where ``A'WA`` is numerically singular for some batch member: ``"raise"``
            (:class:`SingularMatrixError`, the default) or ``"nan"`` (that member's results
            are NaN and flagged in ``result.singular``; the others are as if solved alone).

    Returns:
        :class:`LLSResult`.

    Raises:
        InputValidationError: wrong shapes, non-finite entries, ``M <= p``, invalid weights.
        SingularMatrixError: with ``singular="raise"``, ``A'WA`` is (numerically) singular
            for some batch member; the message names the first such batch index.

    Warns:
        PoorExcitationWarning: ``A'WA`` is ill-conditioned (e.g. a sinusoidal input for a
            20-tap FIR model, notes Fig. 4.1): the estimate is extremely noise-sensitive.
    """
    if not isinstance(A, torch.Tensor) or not isinstance(y, torch.Tensor):
        raise InputValidationError("lls: A and y must be torch tensors.")
    if A.dim() < 2 or y.dim() < 1:
        raise InputValidationError(
            f"lls: A must be (*batch, M, p) and y (*batch, M); got {tuple(A.shape)} and "
            f"{tuple(y.shape)}."
        )
    _check_real("lls: A", A)
    _check_real("lls: y", y)
    if W is not None:
        _check_real("lls: W", W)
    if not A.is_floating_point():
        A = A.to(torch.get_default_dtype())
    y = y.to(dtype=A.dtype, device=A.device)
    M, p = A.shape[-2], A.shape[-1]
    if y.shape[-1] != M:
        raise InputValidationError(
            f"lls: A has {M} rows but y has {y.shape[-1]} samples (last dimension)."
        )
    if M <= p:
        raise InputValidationError(
            f"lls: need more equations than parameters (M = {M}, p = {p}); collect more data "
            "or use a smaller model."
        )
    if method not in ("qr", "cholesky"):
        raise InputValidationError(f"lls: method must be 'qr' or 'cholesky', got {method!r}.")
    _check_singular_option("lls", singular)
    _check_cond_warn("lls", cond_warn)
    batch = _batch_shape("lls", A, "A", 2, y)
    _check_finite("A", A)
    _check_finite("y", y)
    wkind, Wt = _prepare_weights(W, M, A, y.dim())
    skind, S = _prepare_sigma(sigma, M, A, y.dim())
    batch = _extra_batch("W", Wt, wkind, batch, "A and y")
    _extra_batch("sigma", S, skind, batch, "A, y and W")
    dof = _degrees_of_freedom(wkind, Wt, M, p, batch)

    # Whitened problem: ||y - A theta||_W^2 = ||yw - Aw theta||^2.
    if wkind == "diag":
        sw = Wt.sqrt()
        Aw, yw = A * sw.unsqueeze(-1), y * sw
    elif wkind == "full":
        Lt = _cholesky_upper_of_weights(Wt)
        Aw, yw = Lt @ A, (Lt @ y.unsqueeze(-1)).squeeze(-1)
    else:
        Aw, yw = A, y

    eps = torch.finfo(A.dtype).eps
    if method == "qr":
        Q, R = torch.linalg.qr(Aw, mode="reduced")
        col = torch.linalg.vector_norm(R, dim=-2)
        zero_column = (col == 0).any(dim=-1)
        if singular == "raise":
            _raise_if_singular(zero_column)
        s_scaled = torch.linalg.svdvals(R / torch.where(col == 0, 1.0, col).unsqueeze(-2))
        failed = zero_column | (s_scaled[..., -1] <= s_scaled[..., 0] * eps * max(M, p))
        failed = _singular_members(failed, singular)
        if failed is not None:  # the identity stands in for their R; results NaN below
            R = torch.where(
                failed[..., None, None], torch.eye(p, dtype=R.dtype, device=R.device), R
            )
            s_scaled = torch.where(failed.unsqueeze(-1), 1.0, s_scaled)
        s = torch.linalg.svdvals(R)
        scaled_cond = (s_scaled[..., 0] / s_scaled[..., -1]) ** 2
        qty = (Q.transpose(-1, -2) @ yw.unsqueeze(-1)).squeeze(-1)
        theta = torch.linalg.solve_triangular(R, qty.unsqueeze(-1), upper=True).squeeze(-1)
        Rinv = torch.linalg.solve_triangular(
            R, torch.eye(p, dtype=A.dtype, device=A.device).expand_as(R), upper=True
        )
        normal_inverse = Rinv @ Rinv.transpose(-1, -2)
        cond = (s[..., 0] / s[..., -1]) ** 2
    else:
        G = Aw.transpose(-1, -2) @ Aw
        rhs = (Aw.transpose(-1, -2) @ yw.unsqueeze(-1)).squeeze(-1)
        theta, inverse, screened, scaled_cond, failed = _solve_normal_equations(
            G, rhs, M, _warn_threshold(cond_warn, A.dtype), singular
        )
        normal_inverse = inverse.inverse()
        cond = _with_members(
            failed, math.inf, functools.partial(_condition_estimate, G, normal_inverse)
        )
        _warn_poor_excitation(screened, cond_warn, eps * screened, A.dtype)

    residuals = y - (A @ theta.unsqueeze(-1)).squeeze(-1)
    if wkind == "none":
        rw = residuals
    elif wkind == "diag":
        rw = residuals * sw
    else:
        rw = (Lt @ residuals.unsqueeze(-1)).squeeze(-1)
    sigma2 = (rw * rw).sum(-1) / dof
    if method == "qr":
        kappa = scaled_cond.sqrt()
        tan_phi = rw.norm(dim=-1) / (yw - rw).norm(dim=-1).clamp_min(torch.finfo(A.dtype).tiny)
        rounding = eps * (kappa + scaled_cond * tan_phi)
        if failed is not None:  # reported as singular, not as ill-conditioned
            rounding = _fill_members(failed, 0.0, rounding)
        _warn_poor_excitation(scaled_cond, cond_warn, rounding, A.dtype)

    if skind == "none":
        covariance = sigma2[..., None, None] * normal_inverse
    else:
        covariance = _sandwich(A, wkind, Wt, skind, S, normal_inverse)
    standard_errors = torch.diagonal(covariance, dim1=-2, dim2=-1).clamp_min(0).sqrt()
    if failed is not None and method == "qr":  # the Cholesky route's are NaN already
        nan = functools.partial(_fill_members, failed, math.nan)
        theta, standard_errors, sigma2, residuals = map(
            nan, (theta, standard_errors, sigma2, residuals)
        )
        covariance, normal_inverse = nan(covariance), nan(normal_inverse)
        cond = _fill_members(failed, math.inf, cond)
        scaled_cond = _fill_members(failed, math.inf, scaled_cond)
    return LLSResult(
        theta=theta,
        standard_errors=standard_errors,
        sigma2=sigma2,
        dof=dof,
        singular=_singular_mask(failed, theta),
        _covariance=covariance,
        _normal_inverse=normal_inverse,
        _scaled_condition_number=scaled_cond,
        _residuals=residuals,
        _condition_number=cond,
    )


class _ScaledInverse:
    """``G^{-1} = D S^{-1} D`` from the Cholesky factor ``L`` of ``S = D G D``: the triangular
    inverse ``L^{-1}`` (one batched solve) gives ``diag(S^{-1})`` as column sums of squares
    (``S^{-1} = L^{-T} L^{-1}``); the full inverses are formed on first use only."""

    def __init__(self, L: torch.Tensor, dinv: torch.Tensor):
        eye = torch.eye(L.shape[-1], dtype=L.dtype, device=L.device)
        self.Linv = torch.linalg.solve_triangular(L, eye.expand_as(L), upper=False)
        self.dinv = dinv
        self._scaled = None

    def scaled_diagonal(self) -> torch.Tensor:
        """``diag(S^{-1})``, ``(*batch, p)``."""
        return self.Linv.square().sum(-2)

    def scaled(self, where: torch.Tensor | None = None) -> torch.Tensor:
        """``S^{-1}`` (of the batch members selected by the boolean mask ``where``)."""
        if where is not None:
            Linv = self.Linv[where]
            return Linv.transpose(-1, -2) @ Linv
        if self._scaled is None:
            self._scaled = self.Linv.transpose(-1, -2) @ self.Linv
        return self._scaled

    def inverse(self) -> torch.Tensor:
        """``G^{-1}``, ``(*batch, p, p)``."""
        return self.scaled() * (self.dinv.unsqueeze(-1) * self.dinv.unsqueeze(-2))

    def diagonal(self) -> torch.Tensor:
        """``diag(G^{-1})``, ``(*batch, p)``."""
        return self.scaled_diagonal() * self.dinv.square()


def _equilibrated_cholesky(G: torch.Tensor):
    """Cholesky factor ``L`` of ``S = D G D``, ``D = diag(G)^{-1/2}`` (``G = A'WA``, its
    diagonal positive), with ``S``, ``diag(D)`` and ``cholesky_ex``'s ``info``."""
    dinv = torch.diagonal(G, dim1=-2, dim2=-1).rsqrt()
    S = G * (dinv.unsqueeze(-1) * dinv.unsqueeze(-2))
    L, info = torch.linalg.cholesky_ex(S)
    return L, S, dinv, info


def _solve_normal_equations(
    G: torch.Tensor, rhs: torch.Tensor, M: int, cond_warn: float, singular: str = "raise"
):
    """Solve ``G theta = rhs`` (``G = A'WA``) by Cholesky of ``S = D G D``,
    ``D = diag(G)^{-1/2}``.

    Returns ``theta``, the inverse as a :class:`_ScaledInverse`, the screened condition
    numbers of ``S`` (exact estimates where they may exceed ``cond_warn`` or the singularity
    limit, 0 elsewhere; see :func:`_screened_condition`), a callable giving the estimates of
    all of them, and the mask of the members where ``S`` is numerically singular (None where
    none is). Those raise :class:`SingularMatrixError` (``singular="raise"``) or, with
    ``"nan"``, are solved with the identity in place of ``S`` and get NaN ``theta`` and
    inverse, an infinite condition number and a screened one of 0 (no warning).
    """
    p = G.shape[-1]
    eps = torch.finfo(G.dtype).eps
    eye = torch.eye(p, dtype=G.dtype, device=G.device)
    failed = _singular_members((torch.diagonal(G, dim1=-2, dim2=-1) <= 0).any(-1), singular)
    if failed is not None:  # an all-zero regressor
        G = torch.where(failed[..., None, None], eye, G)
    L, S, dinv, info = _equilibrated_cholesky(G)
    not_definite = _singular_members(info != 0, singular)
    if not_definite is not None:
        S = torch.where(not_definite[..., None, None], eye, S)
        L = torch.where(not_definite[..., None, None], eye, L)
        failed = not_definite if failed is None else failed | not_definite
    inverse = _ScaledInverse(L, dinv)
    singular_limit = 1.0 / (eps * max(M, p))
    screened, estimate_all = _screened_condition(S, inverse, min(cond_warn, singular_limit))
    ill = _singular_members(screened >= singular_limit, singular)
    if ill is not None:
        failed = ill if failed is None else failed | ill
    if failed is not None:
        screened = _fill_members(failed, 0.0, screened)
        estimate_all = _with_members(failed, math.inf, estimate_all)
        inverse.dinv = dinv = _fill_members(failed, math.nan, dinv)
    theta = torch.cholesky_solve((rhs * dinv).unsqueeze(-1), L).squeeze(-1) * dinv
    return theta, inverse, screened, estimate_all, failed


def accurate_normal_equations(
    G: torch.Tensor, rhs: torch.Tensor, *, cond_warn: float = DEFAULT_COND_WARN
):
    """Least-squares estimate from the normal equations ``G theta = rhs`` (``G = A'A``,
    ``rhs = A'y``, ``(*batch, p, p)`` and ``(*batch, p)``) where they are as accurate as
    a QR factorisation of ``A`` needs to be, else ``None``.

    The rule: the relative rounding error of the normal-equation estimate is bounded by
    ``eps cond`` (``cond`` the condition number of the column-scaled ``G``, see
    :data:`ROUNDING_WARN`); this solves them (Cholesky of the equilibrated ``G``) when that
    bound is at most :data:`NORMAL_EQUATIONS_ROUNDING` for every batch member, and returns
    ``None`` otherwise (a Cholesky failure, a numerically singular or an ill-conditioned
    member; the caller then uses :func:`lls`'s QR, which also reports singular problems).
    Warns like :func:`lls` (:class:`PoorExcitationWarning`) above ``cond_warn``.

    Returns:
        ``(theta, inverse, scaled_condition)``: the estimate ``(*batch, p)``, ``G^{-1}``
        (``(*batch, p, p)``) and a callable giving the scaled condition numbers
        ``(*batch,)`` (power-iteration estimates, see :func:`_condition_estimate`), or None.
    """
    eps = torch.finfo(G.dtype).eps
    if eps > NORMAL_EQUATIONS_ROUNDING or not bool(torch.isfinite(G.sum() + rhs.sum())):
        return None  # float32 never meets the rule (cond >= 1); non-finite data: lls locates it
    d = torch.diagonal(G, dim1=-2, dim2=-1)
    if bool((d <= 0).any()):
        return None
    L, S, dinv, info = _equilibrated_cholesky(G)
    if bool((info != 0).any()):
        return None
    inverse = _ScaledInverse(L, dinv)
    limit = NORMAL_EQUATIONS_ROUNDING / eps
    screened, estimate_all = _screened_condition(
        S, inverse, min(_warn_threshold(cond_warn, G.dtype), limit)
    )
    if not bool((screened <= limit).all()):  # also catches NaN
        return None
    _warn_poor_excitation(screened, cond_warn, eps * screened, G.dtype)
    theta = torch.cholesky_solve((rhs * dinv).unsqueeze(-1), L).squeeze(-1) * dinv
    return theta, inverse.inverse(), estimate_all


def _screened_condition(S: torch.Tensor, inverse: _ScaledInverse, limit: float):
    """Condition numbers of SPD matrices ``S`` with unit diagonal, estimated only where needed.

    ``lambda_max(S) <= trace(S) = p`` and ``lambda_max(S^{-1}) <= trace(S^{-1})``, so
    ``cond(S) <= p trace(S^{-1})`` costs one pass over ``L^{-1}``. Where that bound (with a
    margin for rounding) is below ``limit``, no threshold test can fire, and the
    power-iteration estimate of :func:`_condition_estimate` is deferred; elsewhere it is
    computed at once (the batch members that are, or may be, poorly conditioned).

    Returns ``screened`` (``(*batch,)``: the estimate where the bound reaches ``limit``, 0
    elsewhere) and a callable returning the estimates of every member (the screened ones
    reused).
    """
    p = S.shape[-1]
    bound = p * inverse.scaled_diagonal().sum(-1)
    doubtful = ~(bound * (1 + 1e-6) < limit)  # also catches NaN
    screened = torch.zeros_like(bound)
    if bool(doubtful.any()):
        screened[doubtful] = _condition_estimate(S[doubtful], inverse.scaled(doubtful))

    def estimate_all() -> torch.Tensor:
        out = screened.clone()
        rest = ~doubtful
        if bool(rest.any()):
            out[rest] = _condition_estimate(S[rest], inverse.scaled()[rest])
        return out

    return screened, estimate_all


def _condition_estimate(S: torch.Tensor, S_inv: torch.Tensor, iters: int = 15) -> torch.Tensor:
    """2-norm condition number ``lambda_max / lambda_min`` of SPD ``S`` by power iteration.

    Rayleigh quotients of ``S`` and ``S^{-1}`` after ``iters`` batched matrix-vector products
    (no per-matrix LAPACK call): a lower bound that is exact when the extreme eigenvalues are
    well separated and accurate to a few digits when they are clustered (then the quotient
    stays inside the cluster). The iterations only find a direction, so a float64 batch runs
    them in float32 on the trace-normalised matrix (half the memory traffic; the direction is
    accurate to ~1e-7, the quotient to ~1e-14); the final Rayleigh quotient is taken in the
    input's precision, so the estimate stays a lower bound. Used by the normal-equation route
    only; the QR route uses the singular values of ``R``.
    """
    p = S.shape[-1]
    low = torch.float32 if S.dtype == torch.float64 else S.dtype
    v0 = 1.0 + torch.arange(p, dtype=low, device=S.device) / (7.0 * p)
    v0 = (v0 / v0.norm()).expand(*S.shape[:-1])
    tiny = torch.finfo(low).tiny

    def top(M):
        trace = torch.diagonal(M, dim1=-2, dim2=-1).sum(-1)
        P = (M / trace[..., None, None]).to(low)
        v = v0
        for _ in range(iters):  # loop over iterations, batched over all matrices
            v = (P * v.unsqueeze(-2)).sum(-1)  # P v, elementwise (fast for small p)
            v = v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(tiny)
        v = v.to(M.dtype)
        return (v * (M @ v.unsqueeze(-1)).squeeze(-1)).sum(-1) / (v * v).sum(-1)

    return top(S) * top(S_inv)


def _warn_threshold(cond_warn: float, dtype: torch.dtype) -> float:
    """Condition number above which :func:`_warn_poor_excitation` warns: ``cond_warn``, or
    fewer than ``-log10(ROUNDING_WARN)`` correct digits in ``dtype``, whichever comes first."""
    return min(cond_warn, ROUNDING_WARN / torch.finfo(dtype).eps)


def _warn_poor_excitation(
    scaled_cond: torch.Tensor, cond_warn: float, rounding: torch.Tensor, dtype
) -> None:
    """Warn where the scaled condition number of ``A'WA`` exceeds ``cond_warn`` or the bound
    ``rounding`` (``(*batch,)``) on the relative rounding error of the estimate exceeds
    :data:`ROUNDING_WARN`; the message gives the correct digits the bound guarantees."""
    bad = (scaled_cond > cond_warn) | (rounding > ROUNDING_WARN)
    if bool(bad.any()):
        idx = _first_index(bad)
        worst = float(scaled_cond[bad].max())
        bound = float(rounding[bad].max())
        eps = torch.finfo(dtype).eps
        name = str(dtype).replace("torch.", "")
        if bound >= 1:
            precision = (
                f"in {name} (eps {eps:.2g}) the rounding-error bound {bound:.2g} leaves NO "
                "guaranteed correct digit in the estimate. Compute in float64 (A.double(), "
                "y.double())"
            )
        else:
            precision = (
                f"in {name} (eps {eps:.2g}) at least about {-math.log10(bound):.0f} correct "
                f"digits remain (relative rounding-error bound {bound:.2g})"
            )
            if dtype != torch.float64 and bound > ROUNDING_WARN:
                precision += "; compute in float64 for more"
        warnings.warn(
            f"lls: A'WA is ill-conditioned (condition number after column scaling "
            f"{worst:.3g}, first at batch index {idx}; warning threshold "
            f"{_warn_threshold(cond_warn, dtype):.3g}): {precision}. "
            "The regressors are nearly collinear, i.e. the input does not excite all "
            "parameters (e.g. a sinusoid for a long FIR model), so the estimate is also very "
            "sensitive to noise. Use a richer input (white noise, PRBS) or fewer parameters.",
            PoorExcitationWarning,
            stacklevel=3,
        )


def _check_singular_option(where: str, singular) -> None:
    if singular not in ("raise", "nan"):
        raise InputValidationError(f"{where}: singular must be 'raise' or 'nan', got {singular!r}.")


def _check_cond_warn(where: str, cond_warn) -> None:
    if (
        isinstance(cond_warn, bool)
        or not isinstance(cond_warn, (int, float))
        or not (cond_warn >= 1)
    ):
        raise InputValidationError(
            f"{where}: cond_warn (the condition number above which it warns) must be a number "
            f">= 1 (math.inf never warns), got {cond_warn!r}."
        )


def _singular_members(mask: torch.Tensor, singular: str) -> torch.Tensor | None:
    """``mask`` (``(*batch,)``, True where a problem is numerically singular), or None where it
    is all False; raises :class:`SingularMatrixError` with ``singular="raise"``."""
    if not bool(mask.any()):
        return None
    if singular == "raise":
        _raise_if_singular(mask)
    return mask


def _fill_members(failed: torch.Tensor, value: float, x: torch.Tensor) -> torch.Tensor:
    """``x`` (``(*batch, ...)``) with the entries of the ``failed`` members set to ``value``."""
    return x.masked_fill(failed.reshape(failed.shape + (1,) * (x.dim() - failed.dim())), value)


def _with_members(failed, value: float, x):
    """:func:`_fill_members` of a tensor, or of what a callable returns (on the call)."""
    if failed is None:
        return x
    if callable(x):
        return lambda: _fill_members(failed, value, x())
    return _fill_members(failed, value, x)


def _singular_mask(failed: torch.Tensor | None, theta: torch.Tensor) -> torch.Tensor:
    """The :attr:`LLSResult.singular` mask: ``failed``, or all False."""
    if failed is None:
        return torch.zeros(theta.shape[:-1], dtype=torch.bool, device=theta.device)
    return failed.expand(theta.shape[:-1])


def _raise_if_singular(singular: torch.Tensor) -> None:
    if bool(singular.any()):
        idx = _first_index(singular)
        n_bad = int(singular.sum())
        raise SingularMatrixError(
            f"lls: A'WA is singular at batch index {idx} ({n_bad} of {singular.numel()} "
            "problems): the regressors are linearly dependent (input not exciting, too few "
            "samples, or duplicated columns). Use a persistently exciting input or remove "
            "parameters."
        )


def _sandwich(A, wkind, Wt, skind, S, P):
    """``P (A'W Sigma W A) P`` (eq. 4.92) without forming any ``M x M`` product needlessly."""
    if wkind == "none":
        WA = A
    elif wkind == "diag":
        WA = A * Wt.unsqueeze(-1)
    else:
        WA = Wt @ A
    if skind == "scalar":
        middle = S * (WA.transpose(-1, -2) @ WA)
    elif skind == "diag":
        middle = WA.transpose(-1, -2) @ (WA * S.unsqueeze(-1))
    else:
        middle = WA.transpose(-1, -2) @ (S @ WA)
    return P @ middle @ P


#: Block length of :func:`_lagged_products`: on CPU, blocks of 8-12 samples run the batched
#: ``L x L`` Gram products faster than longer blocks with the same number of flops
#: (docs/benchmarks.md, "Tuning constants").
_GRAM_BLOCK = 12


@functools.lru_cache(maxsize=32)
def _lag_selection(L: int, nb: int, dtype: torch.dtype, device: torch.device):
    """For each block offset ``q`` of :func:`_lagged_products`: the rows ``[i0, L)`` and
    columns ``[0, j1)`` of ``G_q`` that hold lags ``d = j - i + qL`` in ``[0, nb)`` (for the
    last ``q`` a small lower-left corner), and the 0/1 matrix ``((L - i0) j1, nb)`` summing each
    lag. ``G_0`` needs only ``j >= i``, which its selection matrix encodes."""
    plan = []
    for q in range(-(-(L + nb - 1) // L)):
        i0, j1 = max(0, q * L - nb + 1), min(L, L - 1 + nb - q * L)
        lag = torch.arange(j1, device=device) - torch.arange(i0, L, device=device).unsqueeze(-1)
        hits = (lag + q * L).unsqueeze(-1) == torch.arange(nb, device=device)
        plan.append((q, i0, j1, hits.reshape(-1, nb).to(dtype)))
    return tuple(plan)


def _lagged_products(w: torch.Tensor, z: torch.Tensor, nb: int) -> torch.Tensor:
    """``sum_m w_m z_{m+d}`` for ``d = 0..nb-1`` (``w``, ``z``: ``(*batch, N)``, batch shapes
    broadcast), by batched block Gram matrices: ``O(N nb)`` matmul work, no copy of the signals.

    With the ``K = N // L`` whole blocks ``X_k`` of ``w`` and ``Z_k`` of ``z`` (``L`` samples
    each), ``G_q = sum_k X_k' Z_{k+q}`` for ``q = 0..Q-1`` (``Q = ceil((L + nb - 1) / L)``);
    the pair ``(m, m + d)`` with ``m = kL + i`` sits at ``G_q[i, i + d - qL]`` for the ``q``
    with ``0 <= i + d - qL < L``. Only the entries of ``G_q`` with a lag below ``nb`` are
    formed (see :func:`_lag_selection`) and summed per lag by one matmul with a 0/1 matrix.
    The pairs that end in the last ``N - KL < L`` samples are added directly.
    """
    N = w.shape[-1]
    L = min(_GRAM_BLOCK, N)
    K = N // L
    main = K * L
    X = w[..., :main].unflatten(-1, (K, L))
    Z = z[..., :main].unflatten(-1, (K, L))
    out = None
    for q, i0, j1, select in _lag_selection(L, nb, w.dtype, w.device):  # Q <= 1 + nb / L
        if q >= K:
            break
        G = X[..., : K - q, i0:].transpose(-1, -2) @ Z[..., q:, :j1]
        term = G.flatten(-2) @ select
        out = term if out is None else out + term
    rem = N - main
    if rem:  # pairs (main + t - d, main + t), t < rem: windows of w against the tail of z
        seg = w[..., max(0, main - nb + 1) :]
        seg = F.pad(seg, (nb - 1 + rem - seg.shape[-1], 0))
        windows = seg.unfold(-1, rem, 1)  # window j starts at main - nb + 1 + j: lag nb-1-j
        out = out + (windows * z[..., main:].unsqueeze(-2)).sum(-1).flip(-1)
    return out


def _fir_residuals(u, y, theta, nk: int) -> torch.Tensor:
    """``y - U theta`` for the FIR regressor ``U[k, i] = u_{k-nk-i}`` (exact direct sums)."""
    N = u.shape[-1]
    w = F.pad(u, (nk, 0))[..., :N]
    return y - fir_filter(theta, w)


def fir_lls(
    u: torch.Tensor,
    y: torch.Tensor,
    nb: int,
    nk: int = 0,
    *,
    cond_warn: float = DEFAULT_COND_WARN,
    singular: str = "raise",
) -> LLSResult:
    """Least-squares FIR estimate from rest, without forming the regressor (eq. 4.8–4.11).

    Same result as ``lls(fir_regressor(u, nb, nk), y)`` (``U[k, i] = u_{k-nk-i}``, zero before
    sample 0, all ``N`` rows), but ``U'U`` and ``U'y`` come from correlations: with
    ``w_k = u_{k-nk}``, ``(U'U)_{ij} = r_{|i-j|} - (E'E)_{ij}`` where
    ``r_d = sum_m w_m w_{m+d}`` and ``E`` (``(nb - 1) x nb``, ``E[k, i] = w_{N+k-i}`` for
    ``k < i``) holds the products that fall past the end of the record;
    ``(U'y)_i = c_i = sum_m w_m y_{m+i}``. The lagged products ``r`` and ``c`` come from
    batched Gram matrices of blocks of 12 samples (see :func:`_lagged_products`): ``O(N nb)``
    matmul work per data set, no FFT, no ``N x nb`` regressor. One Cholesky factorisation of
    the column-scaled ``U'U`` gives ``theta`` and its inverse; the standard errors come from
    the diagonal of that inverse, while ``covariance``, ``normal_inverse``, ``residuals`` and
    both condition numbers are formed on first read (the scaled condition number, which
    drives the warning and the singularity test, is estimated at once wherever its upper
    bound ``p trace((D U'U D)^{-1})`` reaches those thresholds). A non-finite sample shows up
    in ``r_0 = w'w`` or ``y'y`` (and the last ``nk`` inputs are summed), so the finite-value
    check costs no extra pass over the data. The residual sum of squares is
    ``r'r = y'y - 2 theta'c + theta'U'U theta``; where that subtraction loses more than three
    digits (``r'r < 1e-3 y'y``, e.g. nearly noise-free data) it is recomputed from explicit
    residuals.

    Args:
        u: inputs ``(*batch, N)``; y: outputs ``(*batch, N)`` (batch shapes broadcast).
        nb: number of taps; nk: input delay.
        cond_warn, singular: as in :func:`lls`.

    Returns:
        :class:`LLSResult` (covariance ``sigma2_hat (U'U)^{-1}``).
    """
    if not isinstance(u, torch.Tensor) or not isinstance(y, torch.Tensor):
        raise InputValidationError("fir_lls: u and y must be torch tensors.")
    _check_real("fir_lls: u", u)
    _check_real("fir_lls: y", y)
    if not u.is_floating_point():
        u = u.to(torch.get_default_dtype())
    y = y.to(dtype=u.dtype, device=u.device)
    N = u.shape[-1]
    if y.shape[-1] != N:
        raise InputValidationError(f"fir_lls: u has {N} samples but y has {y.shape[-1]}.")
    if nb < 1 or nk < 0 or N <= nb:
        raise InputValidationError(
            f"fir_lls: need nb >= 1, nk >= 0 and N > nb; got {nb}, {nk}, {N}."
        )
    _check_singular_option("fir_lls", singular)
    _check_cond_warn("fir_lls", cond_warn)
    batch = _batch_shape("fir_lls", u, "u", 1, y)
    w = F.pad(u, (nk, 0))[..., :N] if nk else u
    r = _lagged_products(w, w, nb)
    c = _lagged_products(w, y, nb)
    yy = (y.unsqueeze(-2) @ y.unsqueeze(-1))[..., 0, 0].expand(batch)
    # a non-finite sample makes w'w (u's last nk samples are not in w) or y'y non-finite:
    # one reduction each instead of extra passes; locate the sample only on failure
    if not bool(torch.isfinite(r[..., 0].sum() + yy.sum() + u[..., N - nk :].sum())):
        _check_finite("u", u, "fir_lls")
        _check_finite("y", y, "fir_lls")
    # Toeplitz part R[i, j] = r_|i-j|, minus the products past the end of the record:
    # C = E'E with E[k, i] = w_{N+k-i} for k < i (nb - 1 rows, built from the last samples).
    s_ = torch.cat([r.flip(-1), r[..., 1:]], dim=-1)  # s_[nb-1+j-i] = r_|i-j|
    R = s_.unfold(-1, nb, 1).flip(-2)
    last = F.pad(w[..., max(0, N - nb + 1) :], (max(0, nb - 1 - N), nb))
    E = last.unfold(-1, nb, 1)[..., : nb - 1, :].flip(-1)  # E[k, i] = last[k + nb-1 - i]
    G = (R - E.transpose(-1, -2) @ E).expand(*batch, nb, nb)
    c = c.expand(*batch, nb)
    theta, inverse, screened, scaled_cond, failed = _solve_normal_equations(
        G, c, N, _warn_threshold(cond_warn, u.dtype), singular
    )
    _warn_poor_excitation(screened, cond_warn, torch.finfo(u.dtype).eps * screened, u.dtype)
    Gtheta = (G @ theta.unsqueeze(-1)).squeeze(-1)
    rss = yy - 2 * (theta * c).sum(-1) + (theta * Gtheta).sum(-1)
    inexact = (rss < 1e-3 * yy).reshape(-1)
    if bool(inexact.any()):  # cancellation: recompute those sums of squares explicitly
        where = inexact.nonzero().squeeze(-1)
        ub, yb = (t.expand(*batch, N).reshape(-1, N)[where] for t in (u, y))
        res = _fir_residuals(ub, yb, theta.reshape(-1, nb)[where], nk)
        rss = rss.reshape(-1).index_put((where,), (res * res).sum(-1)).reshape(batch)
    sigma2 = rss / (N - nb)
    normal_inverse = functools.cache(inverse.inverse)  # (U'U)^{-1}, formed on first use
    variances = sigma2.unsqueeze(-1) * inverse.diagonal()
    return LLSResult(
        theta=theta,
        standard_errors=variances.clamp_min(0).sqrt(),
        sigma2=sigma2,
        dof=N - nb,
        singular=_singular_mask(failed, theta),
        _covariance=lambda: sigma2[..., None, None] * normal_inverse(),
        _normal_inverse=normal_inverse,
        _scaled_condition_number=scaled_cond,
        _residuals=functools.partial(_fir_residuals, u, y, theta, nk),
        _condition_number=_with_members(
            failed, math.inf, lambda: _condition_estimate(G, normal_inverse())
        ),
    )
