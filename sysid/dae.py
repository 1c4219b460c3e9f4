"""Tools for differential-algebraic equations (notes chapter 5), by autograd at given points.

Conventions follow ``integrators.problems``: functions take the time first and the input last,
and are called without the input when ``u is None``:

- fully implicit ``F(t, xdot, x, z[, u]) -> (*batch, n_eq)`` (eq. 5.22; pass ``z`` of width 0
  when there are no algebraic states);
- semi-explicit ``xdot = f(t, x, z[, u])``, ``0 = g(t, x, z[, u])`` (eq. 5.24).

Everything is batched: points are (*batch, n) tensors and the answers are per sample. Samples
must not interact inside the functions (gradients of batch sums are then per-sample).

- :func:`is_dae`: Definition 1, eq. (5.7): dF/d(xdot, zdot) = [dF/dxdot, 0] rank deficient;
- :func:`is_index1`, :func:`is_index1_semi_explicit`: Theorem 9 / Corollary 1 by rank;
- :func:`differential_index`, :func:`semi_explicit_index`: Definition 2 — the number of time
  differentiations after which the equations determine all of (xdot, zdot), found at a point
  from the derivative array [F, dF/dt, ..., d^k F/dt^k] along a polynomial path, all
  derivatives by autograd (inputs held constant);
- :func:`reduce_index`: the procedure of §5.6 for semi-explicit DAEs whose algebraic equations
  free of z can be differentiated along f, returning the index-1 DAE and its consistency
  conditions;
- :func:`eliminate_linear` (eq. 5.30), :func:`linearize_dae` (eq. 5.31-5.32);
- :class:`SingularPerturbation`: eps zdot = g(x, z) and its DAE limit (Theorem 8).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import nn

from integrators.errors import (
    ConvergenceError,
    HighIndexError,
    InputValidationError,
    SingularMatrixError,
)
from integrators.jacobians import jacobian_rows
from integrators.newton import NewtonStatus, minimize, newton

from .mechanics import exact_higher_derivatives


def _call(fn, *args, u=None):
    return fn(*args) if u is None else fn(*args, u)


def _as_time(t, like):
    return torch.as_tensor(0.0 if t is None else t, dtype=like.dtype, device=like.device)


def _zeros_like_width(x, width=0):
    return x.new_zeros(*x.shape[:-1], width)


def _rank(mat, rtol):
    """Numerical rank per sample, relative tolerance on the largest singular value."""
    if mat.shape[-1] == 0 or mat.shape[-2] == 0:
        return torch.zeros(mat.shape[:-2], dtype=torch.long, device=mat.device)
    s = torch.linalg.svdvals(mat)
    return (s > rtol * s[..., :1].clamp_min(torch.finfo(mat.dtype).tiny)).sum(-1)


def _input(u, x, name):
    """``u`` as a (*batch, nu) tensor in ``x``'s dtype, expanded to the batch of ``x``
    (*batch, nx).

    Raises:
        InputValidationError: ``u`` is a scalar (0-dim) or its batch does not broadcast to
            that of ``x``.
    """
    u = torch.as_tensor(u, dtype=x.dtype, device=x.device)
    batch = tuple(x.shape[:-1])
    if u.dim() == 0:
        raise InputValidationError(
            f"{name}: u must have shape (*batch, nu) = ({', '.join(map(str, batch))}"
            f"{', ' if batch else ''}nu), got a scalar; pass one input as a vector of width 1, "
            "e.g. torch.tensor([u]) or u[..., None]."
        )
    try:
        return u.expand(*batch, u.shape[-1])
    except RuntimeError:
        raise InputValidationError(
            f"{name}: u of shape {tuple(u.shape)} does not broadcast to the states' batch "
            f"{batch}; give u the shape (*batch, nu)."
        ) from None


def _points(name, *states):
    """The state tensors (each (*batch_i, n_i)) expanded to their common batch, so that every
    point has its own copy (a leaf shared by the batch would sum the points' Jacobians).

    Raises:
        InputValidationError: the batches do not broadcast.
    """
    try:
        batch = torch.broadcast_shapes(*(s.shape[:-1] for s in states))
    except RuntimeError:
        shapes = ", ".join(str(tuple(s.shape)) for s in states)
        raise InputValidationError(
            f"{name}: the batches of the states {shapes} do not broadcast; give them one "
            "batch (*batch, n)."
        ) from None
    return [s.expand(*batch, s.shape[-1]) for s in states]


def _leaf(x):
    return x.detach().requires_grad_(True)


def is_dae(F, xdot, x, z=None, u=None, *, t=None, rtol=1e-10):
    """Definition 1, eq. (5.7): True where dF/d(xdot, zdot) is rank deficient, (*batch,) bool.

    Algebraic states z contribute zero columns (eq. 5.23), so any F with z of width > 0 is a
    DAE; for z None or of width 0 the test is det(dF/dxdot) = 0 (e.g. eq. 5.3 / 5.11).
    """
    z = _zeros_like_width(x) if z is None else z
    xdot, x, z = _points("is_dae", xdot, x, z)
    with torch.enable_grad():
        xd = _leaf(xdot)
        res = _call(F, _as_time(t, x), xd, x, z, u=u)
        (jac,) = jacobian_rows(res, (xd,))
    n_states = x.shape[-1] + z.shape[-1]
    return (_rank(jac.detach(), rtol) < n_states) | torch.tensor(res.shape[-1] < n_states)


def is_index1(F, xdot, x, z, u=None, *, t=None, rtol=1e-10):
    """Theorem 9: [dF/dxdot, dF/dz] (eq. 5.53) full rank at the points, (*batch,) bool."""
    xdot, x, z = _points("is_index1", xdot, x, z)
    with torch.enable_grad():
        xd, zz = _leaf(xdot), _leaf(z)
        res = _call(F, _as_time(t, x), xd, x, zz, u=u)
        jx, jz = jacobian_rows(res, (xd, zz))
    jac = torch.cat([jx, jz], -1).detach()
    return _rank(jac, rtol) == jac.shape[-1]


def is_index1_semi_explicit(g, x, z, u=None, *, t=None, rtol=1e-10):
    """Corollary 1: dg/dz (eq. 5.56) full rank at the points, (*batch,) bool."""
    x, z = _points("is_index1_semi_explicit", x, z)
    with torch.enable_grad():
        zz = _leaf(z)
        res = _call(g, _as_time(t, x), x, zz, u=u)
        (jz,) = jacobian_rows(res, (zz,))
    return _rank(jz.detach(), rtol) == z.shape[-1]


def _time_derivative(value, s):
    """d value / ds per sample (value (B, m), s (B,)) by two reverse passes (the JVP as the
    derivative of a VJP), keeping the graph for further differentiation."""
    probe = torch.zeros_like(value, requires_grad=True)
    (vjp,) = torch.autograd.grad(value, s, probe, create_graph=True, allow_unused=True)
    if vjp is None:
        return torch.zeros_like(value)
    (jvp,) = torch.autograd.grad(
        vjp, probe, torch.ones_like(vjp), create_graph=True, allow_unused=True
    )
    return torch.zeros_like(value) if jvp is None else jvp


def _derivative_array(F, t, x, z, u, w, order):
    """[F, dF/ds, ..., d^order F/ds^order] at s = 0 along y(s) = y0 + sum_i w_i s^i / i!
    (y = (x, z), w (B, order + 1, n)); returns (B, (order + 1) m)."""
    batch = x.shape[0]
    nx = x.shape[-1]
    s = torch.zeros(batch, dtype=x.dtype, device=x.device, requires_grad=True)
    y = torch.cat([x, z], -1)
    ydot = torch.zeros_like(y)
    power = torch.ones_like(s)  # s^(i-1) / (i-1)!
    for i in range(w.shape[1]):
        ydot = ydot + power[:, None] * w[:, i]
        power = power * s / (i + 1)  # now s^i / i!
        y = y + power[:, None] * w[:, i]
    value = _call(F, t, ydot[:, :nx], y[:, :nx], y[:, nx:], u=u)
    levels = [value]
    for _ in range(order):
        value = _time_derivative(value, s)
        levels.append(value)
    return torch.cat(levels, -1)


def differential_index(F, xdot, x, z, u=None, *, t=None, max_index=5, rtol=1e-8, newton_steps=1):
    """Differential index (Definition 2) of F(t, xdot, x, z[, u]) = 0 at the points (x, z).

    For k = 0, 1, ...: the derivative array [F, ..., d^k F/dt^k] (u held constant) is
    linearised in the unknowns (ydot, yddot, ..., y^(k+1)), y = (x, z), at derivatives made
    consistent by ``newton_steps`` Gauss-Newton steps from ``xdot`` (and zero) of
    :func:`integrators.newton.minimize` (full steps; the rank-deficient ``J^T J`` shifted by
    ``sqrt(eps) I``, which makes them least-norm steps up to that shift); the index is the
    first k for which ydot is uniquely determined (rank of the Jacobian minus the rank of its
    columns for the higher derivatives equals dim y). An ODE has index 0.

    x (*batch, nx), z (*batch, nz) (width 0 allowed), xdot (*batch, nx) a guess, u None or
    (*batch, nu) (a batch that broadcasts). Returns a long tensor (*batch,); raises
    HighIndexError where the index exceeds ``max_index``, InputValidationError for a scalar
    u or one whose batch does not broadcast.
    """
    xdot, x, z = _points("differential_index", xdot, x, z)
    batch = x.shape[:-1]
    rows = batch.numel()  # explicit: a reshape cannot infer it from a width-0 z
    x2, z2 = x.reshape(rows, x.shape[-1]).detach(), z.reshape(rows, z.shape[-1]).detach()
    xd2 = xdot.reshape(rows, x.shape[-1]).detach()
    if u is not None:
        u = _input(u, x, "differential_index")
        u = u.reshape(rows, u.shape[-1])
    n = x2.shape[-1] + z2.shape[-1]
    tt = _as_time(t, x)
    index = torch.full((x2.shape[0],), -1, dtype=torch.long, device=x.device)
    eps = torch.finfo(x.dtype).eps
    for k in range(max_index + 1):

        def array(w, order=k):
            with torch.enable_grad(), exact_higher_derivatives():
                return _derivative_array(F, tt, x2, z2, u, w.reshape(-1, order + 1, n), order)

        w = x2.new_zeros(x2.shape[0], (k + 1) * n)
        w[:, : x2.shape[-1]] = xd2
        fit = minimize(
            array,
            w,
            method="gauss_newton",
            regularization=eps**0.5,
            line_search=False,
            max_iter=newton_steps,
        )
        jac = fit.J
        full = _rank(jac, rtol) - _rank(jac[..., n:], rtol) == n
        index = torch.where((index < 0) & full, torch.full_like(index, k), index)
        if bool((index >= 0).all()):
            return index.reshape(batch)
    bad = torch.nonzero(index < 0)[:5].flatten().tolist()
    raise HighIndexError(
        f"differential index exceeds max_index={max_index} at batch indices {bad} (or the "
        "equations do not determine the trajectory); raise max_index or check the model"
    )


def semi_explicit_index(f, g, x, z, u=None, **kwargs):
    """Differential index of xdot = f(t, x, z[, u]), 0 = g(t, x, z[, u]) (eq. 5.24 via 5.25)."""

    def residual(t, xdot, xx, zz, *uu):
        return torch.cat([xdot - f(t, xx, zz, *uu), g(t, xx, zz, *uu)], -1)

    with torch.no_grad():
        xdot = _call(f, _as_time(kwargs.get("t"), x), x, z, u=u)
    return differential_index(residual, xdot, x, z, u, **kwargs)


@dataclass
class ReducedDAE:
    """Result of :func:`reduce_index`: the index-1 semi-explicit DAE xdot = f, 0 = g and the
    consistency conditions (the algebraic equations that were differentiated, each before its
    differentiation; §5.6), all callables (t, x, z[, u]) -> (*batch, .); the reduced ones
    take t None as t = 0, like the functions of this module."""

    f: object
    g: object
    consistency: object
    differentiations: int
    index: int
    steps: list = field(default_factory=list)


def reduce_index(f, g, x, z, u=None, *, t=None, max_steps=5, rtol=1e-8):
    """Index reduction of §5.6 for a semi-explicit DAE, checked at the sample points (x, z).

    Repeats: if dg/dz is full rank (Corollary 1) stop; else the algebraic equations whose
    z-gradient vanishes at every sample point are replaced by their time derivative along f,
    d/dt g_i = (dg_i/dx) f(t, x, z, u) (step 3-4: xdot substituted by f), and collected as
    consistency conditions. The inputs u must not enter a differentiated equation (their
    derivatives are not available); a rank-deficient dg/dz without such a row cannot be
    reduced by this procedure (it needs algebraic manipulations): both raise HighIndexError.

    x (*batch, nx), z (*batch, nz), u None or (*batch, nu) (a batch that broadcasts; a
    scalar u raises InputValidationError: one input is a vector of width 1).

    Returns :class:`ReducedDAE` with index = differentiations + 1 (eq. 5.81 -> 5.86: 2).
    """
    x, z = _points("reduce_index", x, z)
    tt = _as_time(t, x)
    g_current, conditions, steps = g, [], []
    for step in range(max_steps + 1):
        with torch.enable_grad(), exact_higher_derivatives():
            zz, uu = _leaf(z), None if u is None else _leaf(_input(u, x, "reduce_index"))
            res = _call(g_current, tt, x, zz, u=uu)
            inputs = (zz,) if u is None else (zz, uu)
            jacs = jacobian_rows(res, inputs)
        jz = jacs[0].detach()
        if bool((_rank(jz, rtol) == z.shape[-1]).all()):
            cons = _stack_conditions(conditions)
            return ReducedDAE(f, g_current, cons, step, step + 1, steps)
        scale = jz.abs().amax(dim=(-1, -2), keepdim=True).clamp_min(1.0)
        free = (jz.abs() <= rtol * scale).all(-1)  # (*batch, n_eq)
        free = free.reshape(-1, free.shape[-1]).all(0)
        rows = torch.nonzero(free).flatten().tolist()
        if not rows:
            raise HighIndexError(
                f"reduce_index: dg/dz is rank deficient at step {step} but every algebraic "
                "equation depends on z; this DAE needs algebraic manipulations (a change of "
                "variables) before the §5.6 procedure applies"
            )
        if u is not None and bool(jacs[1].detach()[..., rows, :].abs().gt(rtol).any()):
            raise HighIndexError(
                f"reduce_index: the algebraic equations {rows} depend on the input u; "
                "differentiating them needs du/dt — add du/dt as an input of the model"
            )
        steps.append(rows)
        conditions.append(_select_rows(g_current, rows))
        g_current = _differentiate_rows(f, g_current, rows)
    raise HighIndexError(f"reduce_index: index > {max_steps + 1}; raise max_steps")


def _select_rows(g, rows):
    def selected(t, x, z, *u):
        return g(_as_time(t, x), x, z, *u)[..., rows]

    return selected


def _stack_conditions(conditions):
    def consistency(t, x, z, *u):
        if not conditions:
            return x.new_zeros(*x.shape[:-1], 0)
        tt = _as_time(t, x)
        return torch.cat([c(tt, x, z, *u) for c in conditions], -1)

    return consistency


def _differentiate_rows(f, g, rows):
    """g with the rows ``rows`` replaced by their time derivative along the solution,
    dg_i/dt + (dg_i/dx) f (steps 3-4 of §5.6). A 0-dim time of a batch of states is given to
    ``g`` and ``f`` as one entry per sample, ``(*batch, 1)`` (the form adaptive integrators
    pass), so each sample's dg_i/dt is its own."""

    def g_new(t, x, z, *u):
        with torch.enable_grad(), exact_higher_derivatives():
            xx = x if x.requires_grad else _leaf(x)
            tt = _as_time(t, x)
            if tt.dim() == 0 and x.dim() > 1:
                tt = tt.expand(*x.shape[:-1], 1)
            tt = tt if tt.requires_grad else _leaf(tt)
            res = g(tt, xx, z, *u)
            velocity = f(tt, xx, z, *u)
            out = []
            for i in range(res.shape[-1]):
                if i in rows:
                    gx, gt = torch.autograd.grad(
                        res[..., i].sum(), (xx, tt), create_graph=True, allow_unused=True
                    )
                    along = torch.zeros_like(res[..., i])
                    if gx is not None:
                        along = along + (gx * velocity).sum(-1)
                    if gt is not None:
                        along = along + gt.sum(-1).reshape(along.shape)
                    out.append(along)
                else:
                    out.append(res[..., i])
        return torch.stack(out, -1)

    return g_new


def eliminate_linear(A, B, C, D, E, F, *, rtol=1e-10):
    """Eliminate z from xdot = A x + B u + C z, 0 = D x + E u + F z (eq. 5.29-5.30).

    Returns (A - C F^-1 D, B - C F^-1 E, -F^-1 D, -F^-1 E): xdot = Ar x + Br u and
    z = Cz x + Dz u. Batched over leading dimensions; SingularMatrixError if F is singular
    (the DAE is then not of index 1, Corollary 1): numerically, a singular value of F below
    ``rtol`` times its largest, the rank test of the other functions here.
    """
    if bool((_rank(F, rtol) < F.shape[-1]).any()):
        raise SingularMatrixError(
            "eliminate_linear: F = dg/dz is singular (the DAE is not of index 1: its "
            f"smallest singular value is below rtol = {rtol:g} times its largest); reduce its "
            "index first (sysid.dae.reduce_index)"
        )
    rhs = torch.cat([D, E], -1)
    sol = torch.linalg.solve(F, rhs)
    fd, fe = sol[..., : D.shape[-1]], sol[..., D.shape[-1] :]
    return A - C @ fd, B - C @ fe, -fd, -fe


def linearize_dae(f, g, x, z, u=None, *, t=None):
    """Jacobians of a semi-explicit DAE (eq. 5.32): dict with fx, fz, fu, gx, gz, gu, each
    (*batch, rows, cols) (the u blocks have 0 columns without u); the linearised DAE has the
    form (5.29) and :func:`eliminate_linear` reduces it when gz is invertible.

    x (*batch, nx), z (*batch, nz) (batches that broadcast: each point its own Jacobians), u
    None or (*batch, nu) (a batch that broadcasts; a scalar u raises InputValidationError: one
    input is a vector of width 1)."""
    x, z = _points("linearize_dae", x, z)
    tt = _as_time(t, x)
    with torch.enable_grad():
        xx, zz = _leaf(x), _leaf(z)
        uu = None if u is None else _leaf(_input(u, x, "linearize_dae"))
        inputs = (xx, zz) if u is None else (xx, zz, uu)
        out = {}
        for name, fn in (("f", f), ("g", g)):
            res = _call(fn, tt, xx, zz, u=uu)
            jacs = [j.detach() for j in jacobian_rows(res, inputs)]
            if u is None:
                jacs.append(x.new_zeros(*x.shape[:-1], res.shape[-1], 0))
            out[name + "x"], out[name + "z"], out[name + "u"] = jacs
    return out


def linearize_implicit_dae(F, xdot, x, z, u=None, *, t=None):
    """Jacobians dF/dxdot, dF/dx, dF/dz, dF/du of a fully implicit DAE (eq. 5.31), as a dict
    of (*batch, rows, cols) tensors.

    xdot, x (*batch, nx), z (*batch, nz), u None or (*batch, nu) (a batch that broadcasts; a
    scalar u raises InputValidationError: one input is a vector of width 1)."""
    xdot, x, z = _points("linearize_implicit_dae", xdot, x, z)
    tt = _as_time(t, x)
    with torch.enable_grad():
        leaves = [_leaf(xdot), _leaf(x), _leaf(z)]
        if u is not None:
            leaves.append(_leaf(_input(u, x, "linearize_implicit_dae")))
        res = _call(F, tt, *leaves[:3], u=None if u is None else leaves[3])
        jacs = [j.detach() for j in jacobian_rows(res, tuple(leaves))]
    if u is None:
        jacs.append(x.new_zeros(*x.shape[:-1], res.shape[-1], 0))
    return dict(zip(("Fxdot", "Fx", "Fz", "Fu"), jacs, strict=True))


class SingularPerturbation(nn.Module):
    """The singularly perturbed family xdot = f(t, x, z[, u]), eps zdot = g(t, x, z[, u])
    (eq. 5.33) as an ODE in s = (x, z) (``forward(t, s, u=None)``, usable in ``odeint``), and
    its DAE limit eps -> 0 (eq. 5.35, Theorem 8).

    ``eps`` is an ``nn.Parameter`` broadcasting against the batch (shape () or (*batch, 1)).
    """

    def __init__(self, f, g, nx: int, eps=1e-3):
        super().__init__()
        self.f, self.g, self.nx = f, g, int(nx)
        self.eps = nn.Parameter(torch.as_tensor(eps, dtype=torch.float64))

    def forward(self, t, s, u=None):
        x, z = s[..., : self.nx], s[..., self.nx :]
        eps = self.eps.to(s)
        return torch.cat([_call(self.f, t, x, z, u=u), _call(self.g, t, x, z, u=u) / eps], -1)

    def dae_limit(self):
        """(f, g) of the limit DAE xdot = f, 0 = g (eq. 5.35)."""
        return self.f, self.g

    def tikhonov_conditions(self, x, z, u=None, *, t=None):
        """Theorem 8's hypotheses at the points: (dg/dz invertible, all eigenvalues of dg/dz
        with negative real part), two (*batch,) bool tensors."""
        jac = linearize_dae(self.f, self.g, x, z, u, t=t)["gz"]
        eig = torch.linalg.eigvals(jac)
        invertible = _rank(jac, 1e-10) == z.shape[-1]
        return invertible, (eig.real < 0).all(-1)

    def slow_manifold(self, x, z0, u=None, *, t=None, tol=1e-12, max_iter=50):
        """z on the slow manifold g(t, x, z, u) = 0 by batched Newton from z0 (*batch, nz).

        Full Newton steps of :func:`integrators.newton.newton` in z (exact dg/dz by autograd);
        a member stops once ``|g|_inf <= tol``. Differentiable by the implicit function
        theorem with respect to x, u and every tensor that ``g`` reads (e.g. the parameters
        of the module whose method ``g`` is). Raises SingularMatrixError where dg/dz is singular
        (Theorem 8 fails) and ConvergenceError (naming the samples) after ``max_iter``.
        """
        tt = _as_time(t, x)

        def phi(z, xx, *uu):
            return _call(self.g, tt, xx, z, u=uu[0] if uu else None)

        args = (x,) if u is None else (x, torch.as_tensor(u, dtype=x.dtype))
        res = newton(phi, z0, *args, tol=tol, max_iter=max_iter)
        singular = res.status == NewtonStatus.SINGULAR
        if bool(singular.any()):
            bad = torch.nonzero(singular)[:5].tolist()
            raise SingularMatrixError(
                f"slow_manifold: dg/dz is singular at batch indices {bad} (Theorem 8 fails)"
            )
        if not bool(res.converged.all()):
            bad = torch.nonzero(~res.converged)[:5].tolist()
            raise ConvergenceError(
                f"slow_manifold: |g| > {tol:g} after {max_iter} Newton steps at batch indices "
                f"{bad}; give a better z0"
            )
        return res.x


__all__ = [
    "ReducedDAE",
    "SingularPerturbation",
    "differential_index",
    "eliminate_linear",
    "is_dae",
    "is_index1",
    "is_index1_semi_explicit",
    "linearize_dae",
    "linearize_implicit_dae",
    "reduce_index",
    "semi_explicit_index",
]
