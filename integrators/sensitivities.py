"""Forward sensitivities of fixed-step Runge-Kutta simulations (notes §8).

:func:`sensitivities` differentiates the *discrete* simulation exactly (algorithmic
differentiation, notes §8.2-8.3): for one step of size ``h`` from ``x_k`` with parameters
``q = (p, u_k)``,

    K_i         = f(t_k + c_i h, x_k + h sum_{j<i} a_ij K_j, u_k, p)
    dK_i/dx_k   = F_x^(i) (I + h sum_{j<i} a_ij dK_j/dx_k)                      (eq. 8.17b)
    dK_i/dq     = F_x^(i) (h sum_{j<i} a_ij dK_j/dq) + F_q^(i)                   (eq. 8.17c)
    Phi_k       = I + h sum_i b_i dK_i/dx_k,   Psi_k = h sum_i b_i dK_i/dq
    A_{k+1}     = Phi_k A_k,                    A_0 = I                          (eq. 8.18b)
    B_{k+1}     = Phi_k B_k + Psi_k^p,          B_0 = 0                          (eq. 8.18c)

where ``F_x^(i), F_q^(i)`` are the Jacobians of ``f`` at stage ``i``. The notes' eq. 8.16-8.17
write ``a_sj`` and ``b_j`` inside the stage sums and an identity inside ``dK_i/dp``: typos;
the stage sums use row ``i`` of ``A`` and the parameter derivative has no identity term
(checked against autograd in tests/test_sensitivities.py). Eq. 8.28c likewise has ``dK/dp``
where ``dK/dx_k`` belongs in the propagation factor.

For an implicit tableau the stages solve ``r(K, x_k, q) = 0`` (eq. 8.20) by Newton, and the
implicit function theorem gives all stage derivatives at once (eq. 8.24):
``(I - h [a_ij F_x^(i)]_ij) dK/d(x_k, q) = [F_x^(i) [I 0] + [0 F_q^(i)]]_i``; the same
``Phi_k, Psi_k`` then propagate ``A, B`` (eq. 8.28).

Inputs sampled on the output grid are held piecewise constant (eq. 8.34, ``u(t) = u_k`` on
``[t_k, t_{k+1}]`` for every stage, as ``odeint`` does) and their samples are parameters:
``C[..., k, :, j, :] = dx_k / du_j`` (zero for ``j >= k``).

:func:`variational_sensitivities` integrates the variational equations (eq. 8.8) alongside the
state with :func:`~integrators.odeint.odeint`. With the *same* fixed-step explicit method and
grid the two coincide to rounding (explicit RK discretisation commutes with linearisation; the
notes remark this for Euler in §8.2); with another grid or method (e.g. ``"dopri5"``) the
variational result approximates the exact sensitivities of the ODE, and the difference to the
discrete sensitivities vanishes as the step shrinks.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from .collocation import gauss_legendre, radau_iia
from .errors import ConvergenceError, InputValidationError
from .newton import batch_jacobian, newton
from .tableau import ButcherTableau, tableau

__all__ = ["SensitivityResult", "sensitivities", "variational_sensitivities"]


@dataclass
class SensitivityResult:
    """States and their sensitivities on the output grid (all detached).

    Attributes:
        t: (T,) output times.
        x: (*batch, T, nx) simulated states.
        A: (*batch, T, nx, nx) ``dx_k / dx_0`` (eq. 8.11).
        B: (*batch, T, nx, np) ``dx_k / dp``, or None without parameters.
        C: (*batch, T, nx, T, nu) ``dx_k / du_j`` for sampled inputs (eq. 8.34), else None.
    """

    t: torch.Tensor
    x: torch.Tensor
    A: torch.Tensor
    B: torch.Tensor | None = None
    C: torch.Tensor | None = None


def _model(f: Callable, has_u: bool, has_p: bool) -> Callable:
    """``g(t, x, u, p)`` calling the user's ``f(t, x[, u][, p])``."""

    def g(t, x, u, p):
        args = (t, x) + ((u,) if has_u else ()) + ((p,) if has_p else ())
        return f(*args)

    return g


def _as_tensor(value, like: torch.Tensor, name: str) -> torch.Tensor:
    out = torch.as_tensor(value, dtype=like.dtype, device=like.device).detach()
    if not bool(torch.isfinite(out).all()):
        raise InputValidationError(f"sensitivities: {name} contains non-finite entries.")
    return out


def _prepare(x0, t, p, u):
    if not isinstance(x0, torch.Tensor):
        x0 = torch.as_tensor(x0, dtype=torch.float64)
    x0 = x0.detach()
    if not x0.is_floating_point():
        x0 = x0.to(torch.float64)
    if x0.dim() == 0:
        raise InputValidationError("sensitivities: x0 must have shape (*batch, nx).")
    t = _as_tensor(t, x0, "t")
    if t.dim() != 1 or t.shape[0] < 2 or not bool(torch.all(t[1:] > t[:-1])):
        raise InputValidationError(
            f"sensitivities: t must be a strictly increasing (T,) grid with T >= 2, got shape "
            f"{tuple(t.shape)}."
        )
    if p is not None:
        p = _as_tensor(p, x0, "p")
        if p.dim() == 0:
            p = p.reshape(1)
    if u is not None and not callable(u):
        u = _as_tensor(u, x0, "u")
        if u.dim() < 2 or u.shape[-2] != t.shape[0]:
            raise InputValidationError(
                f"sensitivities: sampled u must have shape (T, nu) or (*batch, T, nu) with "
                f"T = {t.shape[0]}, got {tuple(u.shape)}."
            )
    return x0, t, p, u


def _resolve_tableau(method, stages) -> ButcherTableau:
    if isinstance(method, ButcherTableau):
        return method
    if method in ("gauss_legendre", "radau_iia"):
        s = stages if stages is not None else (2 if method == "gauss_legendre" else 3)
        return gauss_legendre(s) if method == "gauss_legendre" else radau_iia(s)
    return tableau(method)


def _explicit_stages(stage_at, tab, h, x, q, seed):
    """Stages and their derivatives of an explicit step by the recursion of eq. 8.17."""
    nx = x.shape[-1]
    Ks, dKs = [], []
    for i in range(tab.stages):
        xs, dxs = x, seed
        for j in range(i):
            if tab.A[i, j] != 0.0:
                xs = xs + h * float(tab.A[i, j]) * Ks[j]
                dxs = dxs + h * float(tab.A[i, j]) * dKs[j]
        K, J = batch_jacobian(stage_at(i), torch.cat([xs, q], -1))
        dK = J[..., :nx] @ dxs  # chain through the stage state ...
        dK[..., nx:] += J[..., nx:]  # ... plus the direct parameter/input dependence
        Ks.append(K)
        dKs.append(dK)
    return Ks, dKs


def _implicit_stages(stage_at, tab, h, x, q, seed, newton_tol, where):
    """Stages of an implicit step by Newton, derivatives by the IFT (eq. 8.20-8.27)."""
    s, nx = tab.stages, x.shape[-1]
    a = torch.as_tensor(tab.A.copy(), dtype=x.dtype, device=x.device)

    def stage_states(K, x):
        return x[..., None, :] + h * torch.einsum("ij,...jn->...in", a, K)

    def residual(k_flat, x):  # r(K, x_k, q) of eq. 8.20
        K = k_flat.unflatten(-1, (s, nx))
        X = stage_states(K, x)
        F = torch.stack([stage_at(i)(torch.cat([X[..., i, :], q], -1)) for i in range(s)], -2)
        return (F - K).flatten(-2)

    f0 = stage_at(0)(torch.cat([x, q], -1))
    K0 = f0.repeat(*([1] * (f0.dim() - 1)), s)  # every stage starts at f(t_k, x_k)
    res = newton(residual, K0, x, method="full", tol=newton_tol, max_iter=50)
    if not bool(res.converged.all()):
        raise ConvergenceError(
            f"sensitivities: the stage equations (eq. 8.20) of {tab.name!r} did not converge "
            f"{where}: {'; '.join(res.messages)}. Try more substeps."
        )
    K = res.x.unflatten(-1, (s, nx))
    X = stage_states(K, x)
    jac = [batch_jacobian(stage_at(i), torch.cat([X[..., i, :], q], -1))[1] for i in range(s)]
    Fx = torch.stack([J[..., :nx] for J in jac], -3)  # (*batch, s, nx, nx)
    rhs = Fx @ seed[..., None, :, :]  # (*batch, s, nx, nx + nq)
    rhs[..., nx:] += torch.stack([J[..., nx:] for J in jac], -3)
    # (I - h [a_ij F_x^(i)]_ij) dK = rhs: eq. 8.24 with dr/dK = h [a_ij F_x^(i)] - I
    blocks = torch.einsum("ij,...irc->...irjc", a, Fx).flatten(-4, -3).flatten(-2, -1)
    system = torch.eye(s * nx, dtype=x.dtype, device=x.device) - h * blocks
    dK = torch.linalg.solve(system, rhs.flatten(-3, -2)).unflatten(-2, (s, nx))
    return list(K.unbind(-2)), list(dK.unbind(-3))


def sensitivities(
    f: Callable,
    x0,
    t,
    p=None,
    *,
    method: str | ButcherTableau = "rk4",
    u=None,
    substeps: int = 1,
    stages: int | None = None,
    newton_tol: float | None = None,
) -> SensitivityResult:
    """Exact sensitivities of a fixed-step Runge-Kutta simulation (notes eq. 8.13-8.28).

    Explicit tableaus propagate the stage derivatives (eq. 8.17-8.18); implicit ones
    ("gauss_legendre", "radau_iia", "implicit_euler", "implicit_midpoint" or an implicit
    tableau) solve the stage equations by Newton and get the stage derivatives from the
    implicit function theorem (eq. 8.24-8.28).

    Args:
        f: the model ``f(t, x)``, ``f(t, x, u)``, ``f(t, x, p)`` or ``f(t, x, u, p)``
            (``u`` is passed when given, ``p`` when given) returning (*batch, nx); ``t`` is a
            0-dim tensor. ``p`` arrives with shape (*batch, np), so index it as ``p[..., i]``.
        x0: (*batch, nx) initial states.
        t: (T,) strictly increasing output grid.
        p: None, (np,) parameters shared by the batch, or (*batch, np).
        method: a tableau or its name (default "rk4"); ``b_err`` is ignored.
        u: None, input samples (T, nu) or (*batch, T, nu) held piecewise constant on the
            output grid (eq. 8.34; the last sample is not used), or a callable ``u(t)``
            (no input sensitivities then).
        substeps: equal RK steps per output interval.
        stages: number of stages for "gauss_legendre" (default 2) / "radau_iia" (default 3).
        newton_tol: stage-equation tolerance of implicit methods (default of :func:`newton`).

    Returns:
        :class:`SensitivityResult` with ``x``, ``A = dx_k/dx_0``, ``B = dx_k/dp`` and, for
        sampled inputs, ``C = dx_k/du_j``.

    Raises:
        InputValidationError: bad shapes or grid, non-finite data, substeps < 1.
        TableauError: an unknown method.
        ConvergenceError: the stage equations of an implicit method did not converge.
    """
    x0, t, p, u = _prepare(x0, t, p, u)
    tab = _resolve_tableau(method, stages)
    if int(substeps) != substeps or substeps < 1:
        raise InputValidationError(
            f"sensitivities: substeps must be an integer >= 1, got {substeps!r}."
        )
    sampled = isinstance(u, torch.Tensor)
    g = _model(f, u is not None, p is not None)
    nx, n_p = x0.shape[-1], (0 if p is None else p.shape[-1])
    nu = u.shape[-1] if sampled else 0
    batch = torch.broadcast_shapes(
        x0.shape[:-1],
        () if p is None else p.shape[:-1],
        u.shape[:-2] if sampled else (),
    )
    x = x0.expand(*batch, nx).clone()
    eye = torch.eye(nx, dtype=x.dtype, device=x.device)
    T = t.shape[0]
    nq = n_p + nu
    A = eye.expand(*batch, nx, nx).clone()
    B = x.new_zeros(*batch, nx, n_p)
    C = x.new_zeros(*batch, nx, T, nu) if sampled else None
    xs_out, As_out, Bs_out, Cs_out = [x], [A], [B], [C]
    seed = torch.cat([eye, eye.new_zeros(nx, nq)], -1).expand(*batch, nx, nx + nq)
    for k in range(T - 1):
        # q = (p, u_k): the quantities differentiated on this interval, (*batch, nq)
        q = torch.cat(
            ([p.expand(*batch, n_p)] if p is not None else [])
            + ([u[..., k, :].expand(*batch, nu)] if sampled else [])
            + [x.new_zeros(*batch, 0)],
            -1,
        )
        h = (t[k + 1] - t[k]) / substeps
        for m in range(substeps):
            tk = t[k] + m * h

            def stage_at(i, tk=tk, h=h):
                ti = tk + float(tab.c[i]) * h
                u_call = u(ti) if (u is not None and not sampled) else None

                def stage(z):
                    zp = z[..., nx : nx + n_p] if p is not None else None
                    zu = z[..., nx + n_p :] if sampled else u_call
                    return g(ti, z[..., :nx], zu, zp)

                return stage

            if tab.is_explicit:
                Ks, dKs = _explicit_stages(stage_at, tab, h, x, q, seed)
            else:
                where = f"in step {m} of interval {k} (t = {float(tk):.6g})"
                Ks, dKs = _implicit_stages(stage_at, tab, h, x, q, seed, newton_tol, where)
            step = seed.clone()
            for i in range(tab.stages):
                if tab.b[i] != 0.0:
                    x = x + h * float(tab.b[i]) * Ks[i]
                    step = step + h * float(tab.b[i]) * dKs[i]
            Phi, Psi = step[..., :nx], step[..., nx:]  # eq. 8.18b-c / 8.28b-c
            A = Phi @ A
            B = Phi @ B + Psi[..., :n_p]
            if sampled:
                C = (Phi @ C.flatten(-2)).unflatten(-1, (T, nu))
                C[..., k, :] += Psi[..., n_p:]
        xs_out.append(x)
        As_out.append(A)
        Bs_out.append(B)
        Cs_out.append(C)
    return SensitivityResult(
        t=t,
        x=torch.stack(xs_out, -2),
        A=torch.stack(As_out, -3),
        B=None if p is None else torch.stack(Bs_out, -3),
        C=torch.stack(Cs_out, -4) if sampled else None,
    )


def variational_sensitivities(
    f: Callable,
    x0,
    t,
    p=None,
    *,
    method: str | ButcherTableau = "rk4",
    u=None,
    **odeint_options,
) -> SensitivityResult:
    """Sensitivities from the variational equations (notes eq. 8.8), integrated by ``odeint``.

    The augmented state ``(x, vec A, vec B)`` obeys ``x' = f``, ``A' = F_x A`` (A(0) = I),
    ``B' = F_x B + F_p`` (B(0) = 0), with batched autograd Jacobians ``F_x, F_p``.

    Args:
        f, x0, t, p, u: as in :func:`sensitivities` (``u``: samples or a callable; no input
            sensitivities are formed).
        method: any ``odeint`` method, e.g. "rk4" (same discretisation as the simulation:
            identical to :func:`sensitivities`) or "dopri5" (near-exact ODE sensitivities).
        **odeint_options: passed to :func:`~integrators.odeint.odeint` (``substeps``,
            ``rtol``, ``atol``, ``interpolation``, ...).

    Returns:
        :class:`SensitivityResult` with ``x``, ``A`` and ``B`` (``C`` is None).
    """
    from .odeint import odeint

    x0, t, p, u = _prepare(x0, t, p, u)
    g = _model(f, u is not None, p is not None)
    nx, n_p = x0.shape[-1], (0 if p is None else p.shape[-1])
    batch = torch.broadcast_shapes(x0.shape[:-1], () if p is None else p.shape[:-1])
    x0 = x0.expand(*batch, nx)
    eye = torch.eye(nx, dtype=x0.dtype, device=x0.device)

    def augmented(tt, z, *uu):
        x = z[..., :nx]
        A = z[..., nx : nx + nx * nx].unflatten(-1, (nx, nx))
        B = z[..., nx + nx * nx :].unflatten(-1, (nx, n_p))
        zb = z.shape[:-1]
        ui = uu[0] if uu else None
        pb = None if p is None else p.expand(*zb, n_p)
        parts = [x] + ([pb] if p is not None else [])

        def rhs(w):
            return g(tt, w[..., :nx], ui, w[..., nx:] if p is not None else None)

        fx, J = batch_jacobian(rhs, torch.cat(parts, -1))
        Fx, Fp = J[..., :nx], J[..., nx:]
        return torch.cat([fx, (Fx @ A).flatten(-2), (Fx @ B + Fp).flatten(-2)], -1)

    z0 = torch.cat([x0, eye.expand(*batch, nx, nx).flatten(-2), x0.new_zeros(*batch, nx * n_p)], -1)
    with torch.no_grad():
        odeint_options.setdefault("compile", False)  # autograd Jacobians inside the rhs
        sol = odeint(augmented, z0, t, method=method, u=u, **odeint_options)
    z = sol.x
    return SensitivityResult(
        t=t,
        x=z[..., :nx],
        A=z[..., nx : nx + nx * nx].unflatten(-1, (nx, nx)),
        B=None if p is None else z[..., nx + nx * nx :].unflatten(-1, (nx, n_p)),
    )
