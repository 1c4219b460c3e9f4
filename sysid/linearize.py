"""Linearisation of nonlinear state-space models and exact discretisation of LTI systems.

- :func:`linearize`: A, B, C, D of xdot = f(t, x, u), y = h(x, u) (eq. 1.33-1.35) at a batch
  of points (e.g. the samples of a trajectory, batched over time), by reverse-mode autograd
  (one backward pass per output component);
- :func:`steady_state`: batched Newton on f(x, u) = 0 (eq. 1.36);
- :func:`zoh_discretize`: exact zero-order-hold discretisation of xdot = A x + B u over a
  step dt by the matrix exponential of the augmented matrix [[A, B], [0, 0]] dt, which is
  eq. (1.55) with u held constant over the step;
- :func:`simulate_lti_zoh`: the resulting exact reference simulator for piecewise-constant u.
"""

import torch

from integrators.errors import ConvergenceError, InputValidationError, SingularMatrixError
from integrators.jacobians import jacobian_rows
from integrators.newton import NewtonStatus, newton


def _call(f, t, x, u):
    return f(t, x) if u is None else f(t, x, u)


def linearize(f, x, u=None, h=None, t=None):
    """Jacobians A = df/dx, B = df/du, C = dh/dx, D = dh/du (eq. 1.35) at every point.

    f(t, x[, u]) -> (*batch, nx) (called with u only when u is given); h(x[, u]) -> (*batch, ny)
    or None; x (*batch, nx), e.g. the samples of a trajectory (batched over time); u
    (*batch, nu) or None, whose batch broadcasts against that of x (every member is
    linearised at its own point (x, u), e.g. one x_eq with several u_eq); t a scalar
    (default 0). Returns A (*batch, nx, nx), B (*batch, nx, nu)
    (nu = 0 without u), C (*batch, ny, nx) and D (*batch, ny, nu) (None without h). The
    Jacobians are differentiable (autograd graphs) when grad mode is on and x, u or the
    parameters of f require grad. Samples of the batch must not interact in f and h.
    """
    x = torch.as_tensor(x)
    t = torch.as_tensor(0.0 if t is None else t, dtype=x.dtype, device=x.device)
    nx = x.shape[-1]
    if u is not None:
        u = torch.as_tensor(u, dtype=x.dtype, device=x.device)
        if x.dim() < 1 or u.dim() < 1:
            raise InputValidationError(
                f"linearize: x must be (*batch, nx) and u (*batch, nu), got {tuple(x.shape)} "
                f"and {tuple(u.shape)} (a single input is a vector of width 1: u[..., None])."
            )
        try:
            batch = torch.broadcast_shapes(x.shape[:-1], u.shape[:-1])
        except RuntimeError as exc:
            raise InputValidationError(
                f"linearize: the batch shapes of x {tuple(x.shape[:-1])} and u "
                f"{tuple(u.shape[:-1])} do not broadcast; give one point per batch member "
                "or an unbatched x or u shared by all."
            ) from exc
        x, u = x.expand(*batch, nx), u.expand(*batch, u.shape[-1])
    create = torch.is_grad_enabled() and (
        x.requires_grad
        or (u is not None and u.requires_grad)
        or any(p.requires_grad for p in getattr(f, "parameters", lambda: [])())
    )
    with torch.enable_grad():
        xl = x if (x.requires_grad and create) else x.detach().requires_grad_(True)
        ul = None
        if u is not None:
            ul = u if (u.requires_grad and create) else u.detach().requires_grad_(True)
        inputs = (xl,) if u is None else (xl, ul)
        fx = _call(f, t, xl, ul)
        jac = jacobian_rows(fx, inputs, create)
        a = jac[0]
        b = jac[1] if u is not None else x.new_zeros(*x.shape[:-1], nx, 0)
        c = d = None
        if h is not None:
            hx = h(xl) if u is None else h(xl, ul)
            jac_h = jacobian_rows(hx, inputs, create)
            c = jac_h[0]
            d = jac_h[1] if u is not None else x.new_zeros(*x.shape[:-1], hx.shape[-1], 0)
    if not create:
        a, b = a.detach(), b.detach()
        c = None if c is None else c.detach()
        d = None if d is None else d.detach()
    return a, b, c, d


def steady_state(f, x0, u=None, *, tol=1e-10, max_iter=50, t=None):
    """Solve f(t, x, u) = 0 for x by batched Newton from x0 (*batch, nx) (eq. 1.36).

    Full Newton steps of :func:`integrators.newton.newton` (exact Jacobian df/dx by autograd);
    a member stops once ``|f|_inf <= tol``. The result is differentiable by the implicit
    function theorem with respect to ``u`` and to every tensor that ``f`` reads (the
    parameters of an ``nn.Module`` or of the module whose method ``f`` is, tensors in its
    closure).

    Returns x (*batch, nx). Raises SingularMatrixError where df/dx is singular and
    ConvergenceError (naming the samples) when ``|f| > tol`` after max_iter iterations.
    """
    x0 = torch.as_tensor(x0)
    tt = torch.as_tensor(0.0 if t is None else t, dtype=x0.dtype, device=x0.device)
    args = () if u is None else (torch.as_tensor(u, dtype=x0.dtype, device=x0.device),)

    def phi(x, *uu):
        return _call(f, tt, x, uu[0] if uu else None)

    res = newton(phi, x0, *args, tol=tol, max_iter=max_iter)
    singular = res.status == NewtonStatus.SINGULAR
    if bool(singular.any()):
        bad = torch.nonzero(singular)[:5].tolist()
        raise SingularMatrixError(
            f"steady_state: df/dx is singular at batch indices {bad}; the equilibrium "
            "is not isolated there, try another initial guess"
        )
    if not bool(res.converged.all()):
        bad = torch.nonzero(~res.converged)[:5].tolist()
        raise ConvergenceError(
            f"steady_state: |f(x, u)| > {tol:g} after {max_iter} Newton iterations at batch "
            f"indices {bad}; try a better initial guess x0"
        )
    return res.x


def zoh_discretize(a, b, dt):
    """Exact ZOH discretisation (eq. 1.55 with u constant over a step).

    a (*batch, n, n), b (*batch, n, m) (finite), dt a float or tensor broadcasting against
    ``*batch`` (finite, > 0). Returns (Ad, Bd) = (e^{A dt}, int_0^dt e^{A s} ds B) from one
    matrix exponential of the augmented matrix [[A, B], [0, 0]] dt.
    """
    a, b = torch.as_tensor(a), torch.as_tensor(b)
    if a.dim() < 2 or b.dim() < 2 or a.shape[-1] != a.shape[-2] or b.shape[-2] != a.shape[-1]:
        raise InputValidationError(
            f"zoh_discretize: A must be (*, n, n) and B (*, n, m), got {tuple(a.shape)}, "
            f"{tuple(b.shape)} (a single input column is B[:, None])."
        )
    for name, x in (("A", a), ("B", b)):
        if not bool(torch.isfinite(x).all()):
            idx = tuple(int(i) for i in torch.nonzero(~torch.isfinite(x))[0])
            raise InputValidationError(
                f"zoh_discretize: {name} has a non-finite entry ({float(x[idx])} at index {idx}); "
                "the matrix exponential of a system with inf/NaN coefficients is undefined."
            )
    n, m = b.shape[-2], b.shape[-1]
    dt = torch.as_tensor(dt, dtype=a.dtype, device=a.device)
    bad = ~(torch.isfinite(dt) & (dt > 0))
    if bool(bad.any()):
        raise InputValidationError(
            f"zoh_discretize: the step dt must be finite and > 0 (in the time units of A), "
            f"got {float(dt[bad][0])} (dt {tuple(dt.shape)}, first bad entry)."
        )
    try:
        batch = torch.broadcast_shapes(a.shape[:-2], b.shape[:-2], dt.shape)
    except RuntimeError as exc:
        raise InputValidationError(
            f"zoh_discretize: the batch shapes of A {tuple(a.shape[:-2])}, B "
            f"{tuple(b.shape[:-2])} and dt {tuple(dt.shape)} do not broadcast."
        ) from exc
    a, b = a.expand(*batch, n, n), b.expand(*batch, n, m)
    top = torch.cat([a, b], -1)
    aug = torch.cat([top, a.new_zeros(*batch, m, n + m)], -2)
    phi = torch.linalg.matrix_exp(aug * dt[..., None, None])
    return phi[..., :n, :n], phi[..., :n, n:]


def simulate_lti_zoh(a, b, x0, u, dt, c=None, d=None):
    """Exact samples of xdot = A x + B u with u held constant over each step (reference).

    a (*batch, n, n), b (*batch, n, m) (finite), dt a float or tensor (*batch) (finite,
    > 0), x0 (*batch, n), u (*batch, T, m), c (*batch, p, n) and d (*batch, p, m) or None:
    the batch shapes broadcast against each other (e.g. an unbatched x0 (n,) and u (T, m)
    start every system of a batched A or dt). Returns x (*batch, T + 1, n) (x_0 .. x_T)
    and, when c is given, y_k = C x_k + D u_k (*batch, T, p) (D = 0 when d is None).
    """
    ad, bd = zoh_discretize(a, b, dt)
    n, m = bd.shape[-2], bd.shape[-1]
    u = torch.as_tensor(u, dtype=ad.dtype)
    x0 = torch.as_tensor(x0, dtype=ad.dtype)
    if u.dim() < 2 or u.shape[-1] != m or x0.shape[-1:] != (n,):
        raise InputValidationError(
            f"simulate_lti_zoh: u must be (*batch, T, m) with m = {m} and x0 "
            f"(*batch, n) with n = {n}, got {tuple(u.shape)} and {tuple(x0.shape)}."
        )
    if c is not None:
        c = torch.as_tensor(c, dtype=ad.dtype)
        p = c.shape[-2] if c.dim() >= 2 else None
        if p is None or c.shape[-1] != n:
            raise InputValidationError(
                f"simulate_lti_zoh: C must be (*batch, p, n) with n = {n}, got "
                f"{tuple(c.shape)} (a single output row is C[None, :])."
            )
        if d is not None:
            d = torch.as_tensor(d, dtype=ad.dtype)
            if d.dim() < 2 or d.shape[-2:] != (p, m):
                raise InputValidationError(
                    f"simulate_lti_zoh: D must be (*batch, p, m) = (*batch, {p}, {m}) to "
                    f"match C {tuple(c.shape)} and B {tuple(bd.shape)}, got {tuple(d.shape)}."
                )
    shapes = {"A/B/dt": ad.shape[:-2], "x0": x0.shape[:-1], "u": u.shape[:-2]}
    if c is not None:
        shapes["C"] = c.shape[:-2]
        if d is not None:
            shapes["D"] = d.shape[:-2]
    try:
        batch = torch.broadcast_shapes(*shapes.values())
    except RuntimeError as exc:
        got = ", ".join(f"{k} {tuple(v)}" for k, v in shapes.items())
        raise InputValidationError(
            f"simulate_lti_zoh: the batch shapes of {got} do not broadcast; give x0 and u "
            "either without batch dimensions or with the batch of the systems."
        ) from exc
    ad, bd = ad.expand(*batch, n, n), bd.expand(*batch, n, m)
    u = u.expand(*batch, *u.shape[-2:])
    xs = [x0.expand(*batch, n)]
    for k in range(u.shape[-2]):
        xs.append((ad @ xs[-1].unsqueeze(-1) + bd @ u[..., k, :].unsqueeze(-1)).squeeze(-1))
    x = torch.stack(xs, -2)
    if c is None:
        return x
    y = (c.unsqueeze(-3) @ x[..., :-1, :].unsqueeze(-1)).squeeze(-1)
    if d is not None:
        y = y + (d.unsqueeze(-3) @ u.unsqueeze(-1)).squeeze(-1)
    return x, y
