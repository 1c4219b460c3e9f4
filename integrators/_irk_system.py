"""One residual form for every problem class solved by the implicit Runge-Kutta methods.

Each stage ``i`` of a step has unknowns ``W_i = (K_i, Z_i)`` (stage derivative, algebraic
stage; ``p = n + m`` entries) and stage state ``X_i = x_k + dt sum_j a_ij K_j``. The stage
residual ``R_i = r(t_i, K_i, X_i, Z_i, u_i)`` is

- explicit ODE ``x' = f(t, x, u)``:                ``K - f(t, X, u)``             (eq. 7.14)
- semi-explicit DAE ``x' = f, 0 = g``:             ``[K - f(t, X, Z, u); g(...)]`` (eq. 7.63)
- implicit ODE / DAE ``F(t, x', x[, z], u) = 0``: ``F(t, K, X[, Z], u)``         (eq. 7.52, 7.56)

and its derivative blocks ``E = [dr/dK, dr/dZ]``, ``G = [dr/dX, 0]`` (both (p, p)) define the
Newton matrix (see ``_irk_linalg``). Jacobians are computed by reverse-mode autograd for the
whole batch (the batch stays a batch, so parameters that broadcast against it keep working):
one backward pass on ``p`` stacked copies of the point when the functions broadcast over a
leading extra dimension, else one backward pass per residual component.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from .jacobians import batch_jacobian


def root_derivatives(phi, v_star):
    """The converged root ``v_star`` of ``phi(v) = 0`` with its first and second derivatives
    with respect to everything ``phi`` uses (``x0``, module parameters, captured tensors;
    :func:`~integrators.newton.root_with_derivatives`, exact Jacobian at the root). A member
    whose Jacobian is singular there (a stopped sample solved at placeholder values, its
    result unused) gets non-finite derivatives of its own; the others are unaffected."""
    from .newton import root_with_derivatives

    if not torch.is_grad_enabled():
        return v_star
    with torch.enable_grad():
        r = phi(v_star)
    if not r.requires_grad:
        return v_star
    _, J = batch_jacobian(phi, v_star)
    lu, piv, _ = torch.linalg.lu_factor_ex(J)
    return root_with_derivatives(
        phi, v_star, lambda b: torch.linalg.lu_solve(lu, piv, b[..., None])[..., 0], r_star=r
    )


class StageSystem:
    """The residual ``r`` of one problem class.

    Args:
        kind: "ode", "semi" or "implicit".
        n, m: numbers of differential and algebraic states.
        fns: ``(f,)`` for "ode", ``(f, g)`` for "semi", ``(F,)`` for "implicit".
        has_input: whether the user's functions take ``u`` as last argument.
    """

    def __init__(self, kind: str, n: int, m: int, fns: tuple, has_input: bool):
        self.kind, self.n, self.m = kind, n, m
        self.fns = fns
        self.has_input = has_input
        self.stack_jacobian: dict = {}  # v.dim() -> whether the stacked Jacobian matches

    @property
    def p(self) -> int:
        return self.n + self.m

    def _call(self, fn, t, *args, u=None):
        return fn(t, *args, u) if self.has_input else fn(t, *args)

    def algebraic_states(self, t, x, z, u, xdot=None):
        """The algebraic states consistent with the differential states ``x`` at time ``t``
        (notes eq. 5.53-5.58): the root ``z`` of ``g(t, x, z) = 0`` (semi-explicit), or
        ``(x', z)`` of ``F(t, x', x, z) = 0`` (implicit), by damped Newton from ``z`` (and
        ``xdot``, zeros when None); the root carries its first and second derivatives with
        respect to ``x`` and everything the model uses (:func:`root_derivatives`).

        Returns:
            ``(xdot, z, result)``: (*batch, n) ``x'`` (``f(t, x, z)`` for the semi-explicit
            kind), (*batch, m) ``z`` and the :class:`~integrators.newton.NewtonResult`.
        """
        from .newton import newton

        n, xd = self.n, x.detach()
        if self.kind == "semi":

            def phi(v, x):
                return self._call(self.fns[1], t, x, v, u=u)

            guess = z.detach()
        else:

            def phi(v, x):
                return self.residual(t, v[..., :n], x, v[..., n:], u)

            start = torch.zeros_like(xd) if xdot is None else xdot.detach()
            guess = torch.cat([start, z.detach()], dim=-1)
        # rows equilibrated by their largest Jacobian entry at the guess: Newton's absolute
        # residual test then bounds the error of the root, whatever the scale of g (or F)
        J = batch_jacobian(lambda v: phi(v, xd), guess, strategy="rows")[1]
        scale = J.abs().amax(-1).clamp_min(torch.finfo(J.dtype).tiny)

        def equilibrated(v, x):
            return phi(v, x) / scale

        # derivatives from root_derivatives, not from the solve
        res = newton(equilibrated, guess, xd, method="damped", max_iter=50, params=())
        v = root_derivatives(lambda v: phi(v, x), res.x)
        if self.kind == "semi":
            return self.rhs_f(t, x, v, u), v, res
        return v[..., :n], v[..., n:], res

    def rhs_f(self, t, x, z, u):
        """``f(t, x[, z], u)`` for the explicit kinds (the derivative at a consistent point)."""
        if self.kind == "ode":
            return self._call(self.fns[0], t, x, u=u)
        return self._call(self.fns[0], t, x, z, u=u)

    def residual(self, t, K, X, Z, u) -> torch.Tensor:
        """Stage residual (*batch, p) for K, X (*batch, n) and Z (*batch, m) (m may be 0)."""
        if self.kind == "ode":
            return K - self._call(self.fns[0], t, X, u=u)
        if self.kind == "semi":
            f = self._call(self.fns[0], t, X, Z, u=u)
            g = self._call(self.fns[1], t, X, Z, u=u)
            return torch.cat([K - f, g], dim=-1)
        if self.m == 0:
            return self._call(self.fns[0], t, K, X, u=u)
        return self._call(self.fns[0], t, K, X, Z, u=u)

    def jacobian(self, fun: Callable, v: torch.Tensor) -> torch.Tensor:
        """The Jacobian (*batch, p, d) of the sample-wise ``fun`` at ``v`` by
        :func:`~integrators.jacobians.batch_jacobian`: one backward pass on stacked copies
        (``"stacked"``) when that reproduced the row-by-row Jacobian (``"rows"``) at the
        first call with that number of dimensions of ``v``
        (checked once per system, like the stage stacking of ``IRKCore.residual``; the two
        agree to the last bit for elementwise models), else row by row."""
        stackable = self.stack_jacobian.get(v.dim())
        if stackable is not None:
            strategy = "stacked" if stackable else "rows"
            return batch_jacobian(fun, v, strategy=strategy, outputs=self.p)[1]
        ref = batch_jacobian(fun, v, strategy="rows")[1]
        try:
            got = batch_jacobian(fun, v, strategy="stacked", outputs=self.p)[1]
            tol = 1e3 * torch.finfo(v.dtype).eps
            stackable = got.shape == ref.shape and bool(
                torch.allclose(got, ref, rtol=tol, atol=tol, equal_nan=True)
            )
        except Exception:  # noqa: BLE001 - any failure means "not stackable"
            stackable = False
        self.stack_jacobian[v.dim()] = stackable
        return ref

    def blocks(self, t, K, X, Z, u):
        """Derivative blocks ``E, G`` (*batch, p, p) and the index-check matrix.

        Returns:
            ``(E, G, index_matrix, reference)``: ``index_matrix`` is ``dg/dz`` (semi-explicit,
            Corollary 1, eq. 5.56) or ``[dF/dx', dF/dz]`` (implicit, Theorem 9, eq. 5.53), None
            for explicit ODEs; ``reference`` is the full Jacobian whose norm scales the
            rank test.
        """
        n, p, batch = self.n, self.p, X.shape[:-1]
        if self.kind == "ode":
            Jf = self.jacobian(lambda x: self._call(self.fns[0], t, x, u=u), X)
            eye_n = torch.eye(n, dtype=X.dtype, device=X.device).expand(*batch, n, n)
            return eye_n, -Jf, None, None
        if self.kind == "semi":

            def fg(v):
                x, z = v[..., :n], v[..., n:]
                f = self._call(self.fns[0], t, x, z, u=u)
                g = self._call(self.fns[1], t, x, z, u=u)
                return torch.cat([f, g], dim=-1)

            J = self.jacobian(fg, torch.cat([X, Z], dim=-1))
            D = torch.cat([-J[..., :n, :], J[..., n:, :]], dim=-2)  # dR/d(X, Z) of [K - f; g]
            dR_dK = torch.eye(p, n, dtype=X.dtype, device=X.device).expand(*batch, p, n)
            E = torch.cat([dR_dK, D[..., n:]], dim=-1)
            G = torch.cat([D[..., :n], torch.zeros_like(D[..., n:])], dim=-1)
            return E, G, J[..., n:, n:], J[..., n:, :]

        def F(v):
            k, x, z = v[..., :n], v[..., n : 2 * n], v[..., 2 * n :]
            return self.residual(t, k, x, z, u)

        J = self.jacobian(F, torch.cat([K, X, Z], dim=-1))
        FK, FX, FZ = J[..., :n], J[..., n : 2 * n], J[..., 2 * n :]
        E = torch.cat([FK, FZ], dim=-1)
        G = torch.cat([FX, torch.zeros_like(FZ)], dim=-1)
        return E, G, E, J


def rank_ratio(index_matrix: torch.Tensor, reference: torch.Tensor, scale_cap=None) -> torch.Tensor:
    """Smallest singular value of ``index_matrix`` relative to the norm of ``reference``.

    The norm of the full Jacobian makes the test invariant to a rescaling of the residual.
    ``scale_cap`` ((*batch,), the norm at the start of the integration) caps that norm: on a
    solution that escapes to infinity the Jacobian's norm grows with the states (``dg/dx``
    for ``g = z - x^3``) while ``dg/dz`` stays regular, and such a growth alone must not pass
    for a loss of rank.

    Returns:
        (*batch,) ratios; 0 for an exactly rank-deficient (e.g. zero) index matrix, inf where
        either matrix has a non-finite entry (no rank statement is possible there).
    """
    index_matrix, reference = index_matrix.detach(), reference.detach()
    finite = torch.isfinite(index_matrix).flatten(-2).all(-1) & torch.isfinite(reference).flatten(
        -2
    ).all(-1)
    sv = torch.linalg.svdvals(torch.where(finite[..., None, None], index_matrix, 0.0))
    scale = torch.linalg.matrix_norm(torch.where(finite[..., None, None], reference, 0.0), ord=2)
    if scale_cap is not None:
        scale = torch.minimum(scale, scale_cap)
    ratio = sv[..., -1] / scale.clamp_min(torch.finfo(index_matrix.dtype).tiny)
    return torch.where(finite, ratio, torch.inf)


def jacobian_scale(reference: torch.Tensor) -> torch.Tensor:
    """(*batch,) spectral norm of the full Jacobian (inf where it is not finite): the
    ``scale_cap`` of :func:`rank_ratio` measured at the start of an integration."""
    reference = reference.detach()
    finite = torch.isfinite(reference).flatten(-2).all(-1)
    norm = torch.linalg.matrix_norm(torch.where(finite[..., None, None], reference, 0.0), ord=2)
    return torch.where(finite, norm, torch.inf)
