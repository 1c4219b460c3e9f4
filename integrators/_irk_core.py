"""The implicit Runge-Kutta step shared by the fixed-step and the adaptive drivers.

One step solves the stage equations ``R(W) = 0`` (notes eq. 7.14, 7.52, 7.56, 7.63) for the
stage unknowns ``W = (K, Z)`` of shape (*batch, s, p) by simplified Newton: the iteration
matrix is frozen at one point and factorised once (see ``_irk_linalg``), and the contraction
rate ``theta = ||dW_k|| / ||dW_{k-1}||`` decides convergence (``eta ||dW|| <= tol`` with
``eta = theta / (1 - theta)``), divergence and whether the factorisation may be reused.

Gradients use the implicit function theorem (eq. 3.40): with ``W*`` the converged stages,
``W = W* + (D - stop_grad(D))`` with ``D = -J(W*)^{-1} R(W*, x_k, theta)`` has the value ``W*``
and the derivative ``dW/d(x_k, theta) = -J^{-1} dR/d(x_k, theta)``; ``J^{-1}`` is applied by
:class:`FrozenLUSolve`, whose backward is one transposed solve with the exact stage Jacobian.
Nothing of the Newton iterations is stored.
"""

from __future__ import annotations

import numpy as np
import torch

from ._irk_linalg import StageLinearSolver
from ._irk_system import StageSystem, rank_ratio
from .newton import newton

EPS = {
    torch.float64: float(np.finfo(np.float64).eps),
    torch.float32: float(np.finfo(np.float32).eps),
}


class FrozenLUSolve(torch.autograd.Function):
    """``y = M^{-1} b`` for a fixed LU factorisation; backward is ``M^{-T} grad`` (one solve)."""

    @staticmethod
    def forward(ctx, lu, pivots, b):
        ctx.save_for_backward(lu, pivots)
        return torch.linalg.lu_solve(lu, pivots, b)

    @staticmethod
    def backward(ctx, grad):
        lu, pivots = ctx.saved_tensors
        return None, None, torch.linalg.lu_solve(lu, pivots, grad, adjoint=True)


class InputSignal:
    """Stage inputs read from a ``BoundRHS`` (contract C1), or none.

    Args:
        source: None or a bound rhs with ``kind`` / ``u`` / ``input_at`` (``bind_rhs``).
    """

    def __init__(self, source):
        self.source = source

    def at(self, t, t_step=None):
        """Input at time ``t``; a zero-order-hold signal on a fixed step holds ``u(t_step)``
        over the closed step (eq. 8.34), so a stage with ``c_i = 1`` still sees ``u_k``."""
        src = self.source
        if src is None or src.kind == "none":
            return None
        if src.kind == "callable":
            return src.u(t)
        if src.kind == "zoh" and t_step is not None:
            return src.input_at(t_step)
        return src.input_at(t)


class IRKCore:
    """Tableau, problem residual and linear algebra of one integration.

    Args:
        tab: implicit ButcherTableau.
        system: the :class:`StageSystem`.
        signal: :class:`InputSignal`.
        dtype, device: of the states.
        linear_solver: "auto", "transformed" or "full" (see ``StageLinearSolver``).
    """

    def __init__(
        self,
        tab,
        system: StageSystem,
        signal: InputSignal,
        dtype,
        device,
        linear_solver: str = "auto",
    ):
        self.tab, self.system, self.signal = tab, system, signal
        self.s = tab.stages
        self.A = torch.as_tensor(np.array(tab.A), dtype=dtype, device=device)
        self.b = torch.as_tensor(np.array(tab.b), dtype=dtype, device=device)
        self.c = [float(ci) for ci in tab.c]
        self.solver = StageLinearSolver(np.array(tab.A), dtype, device, mode=linear_solver)
        self.eps = EPS.get(dtype, EPS[torch.float32])
        self.n_f_evals = 0
        self.needs_grad = None

    # ------------------------------------------------------------------ stages
    def stage_times(self, tk, h):
        """Stage times ``t_k + c_i h``; ``tk``/``h`` 0-dim (shared) or (*batch, 1)."""
        return [tk + ci * h for ci in self.c]

    def stage_inputs(self, times, tk, fixed: bool):
        return [self.signal.at(ti, tk if fixed else None) for ti in times]

    def stage_states(self, xk, h, K):
        """``X_i = x_k + h sum_j a_ij K_j``: (*batch, s, n); h is (*batch,)."""
        return xk[..., None, :] + h[..., None, None] * (self.A @ K)

    def residual(self, times, inputs, h, xk, W):
        """Stage residuals (*batch, s, p) of the stage unknowns ``W`` (*batch, s, p)."""
        n = self.system.n
        K, Z = W[..., :n], W[..., n:]
        X = self.stage_states(xk, h, K)
        self.n_f_evals += self.s
        return torch.stack(
            [
                self.system.residual(times[i], K[..., i, :], X[..., i, :], Z[..., i, :], inputs[i])
                for i in range(self.s)
            ],
            dim=-2,
        )

    def step_end(self, xk, h, W):
        """``x_{k+1} = x_k + h sum_i b_i K_i`` (eq. 7.18): (*batch, n)."""
        K = W[..., : self.system.n]
        return xk + h[..., None] * (self.b @ K)

    # ------------------------------------------------------------------ Newton
    def scaled_norm(self, h, dW, sc_x, sc_z):
        """RMS of the state increments ``h A dK / sc_x`` and ``dZ / sc_z``: (*batch,)."""
        n = self.system.n
        dX = h[..., None, None] * (self.A @ dW[..., :n])
        parts = [(dX / sc_x[..., None, :]).square().flatten(-2)]
        if self.system.m:
            parts.append((dW[..., n:] / sc_z[..., None, :]).square().flatten(-2))
        return torch.cat(parts, dim=-1).mean(-1).sqrt()

    def newton(
        self, times, inputs, h, xk, W, factors, sc_x, sc_z, tol, max_iter, active, predict=True
    ):
        """Simplified Newton on the stage equations, per sample.

        Convergence needs a measured contraction rate ``theta`` (two iterations, as in
        scipy's Radau) unless the update is exactly zero: ``theta / (1 - theta) ||dW|| <= tol``.
        A member stops as failed when ``theta >= 1`` or (``predict=True``, used where a
        smaller step is the remedy) when the rate predicts that ``max_iter`` iterations will
        not reach ``tol``.

        Args:
            times, inputs: stage times and inputs.
            h: (*batch,) step sizes; xk (*batch, n); W (*batch, s, p) initial guess.
            factors: from ``StageLinearSolver.factorize``.
            sc_x, sc_z: (*batch, n), (*batch, m) error scales ``atol + rtol |.|``.
            tol: convergence tolerance in the scaled norm.
            max_iter: iteration limit.
            active: (*batch,) bool: samples to solve (others are left untouched).

        Returns:
            ``(W, converged, iterations, theta, non_finite)``, per-sample tensors (no autograd
            graph: gradients come from :meth:`ift`).
        """
        with torch.no_grad():
            return self._newton(
                times, inputs, h, xk, W, factors, sc_x, sc_z, tol, max_iter, active, predict
            )

    def _newton(self, times, inputs, h, xk, W, factors, sc_x, sc_z, tol, max_iter, active, predict):
        batch = h.shape
        done = ~active
        failed = torch.zeros(batch, dtype=torch.bool, device=h.device)
        non_finite = torch.zeros_like(failed)
        iters = torch.zeros(batch, dtype=torch.int64, device=h.device)
        theta = torch.zeros(batch, dtype=h.dtype, device=h.device)
        norm_old = None
        for it in range(max_iter):
            R = self.residual(times, inputs, h, xk, W)
            dW = self.solver.solve(factors, R, h)
            finite = torch.isfinite(dW).flatten(-2).all(-1)
            norm = self.scaled_norm(h, dW, sc_x, sc_z)
            running = ~done & ~failed
            bad = running & ~finite
            non_finite |= bad
            failed |= bad
            running = running & ~bad
            if norm_old is not None:
                th = norm / norm_old.clamp_min(torch.finfo(h.dtype).tiny)
                theta = torch.where(running, th, theta)
                hopeless = th >= 1.0
                if predict:
                    slow = th.pow(max_iter - it) / (1.0 - th).clamp_min(1e-12) * norm > tol
                    hopeless = hopeless | slow
                hopeless = running & hopeless
                failed |= hopeless
                running = running & ~hopeless
                conv = running & ((norm == 0) | (th / (1.0 - th) * norm <= tol))
            else:
                conv = running & (norm == 0)
            W = torch.where(running[..., None, None], W + torch.nan_to_num(dW), W)
            iters += running.long()
            done |= conv
            norm_old = norm
            if not bool((~done & ~failed).any()):
                break
        converged = done & active
        return W, converged, iters, theta, non_finite

    def damped_newton(self, times, inputs, h, xk, W, active, tol, max_iter=50):
        """Fallback for a fixed step whose simplified Newton failed (a fixed step cannot be
        shortened): damped Newton with the exact stage Jacobian at every iterate (notes
        Theorem 4) on the flattened stage residual.

        Args:
            h (*batch,), xk (*batch, n), W (*batch, s, p): as in :meth:`newton`.
            active: (*batch,) bool: the members to solve.
            tol: residual tolerance ``||R||_inf`` (derivative units).

        Returns:
            ``(W, converged, iterations)``; members outside ``active`` keep ``W`` and report
            zero iterations. No autograd graph (gradients come from :meth:`ift`).
        """
        stage_shape = W.shape[-2:]

        def phi(w):
            return self.residual(times, inputs, h, xk, w.unflatten(-1, stage_shape)).flatten(-2)

        with torch.no_grad():
            res = newton(phi, W.detach().flatten(-2), method="damped", tol=tol, max_iter=max_iter)
        converged = res.converged & active
        W_new = torch.where(active[..., None, None], res.x.detach().unflatten(-1, stage_shape), W)
        return W_new, converged, res.iterations * active

    # --------------------------------------------------------------- Jacobians
    def frozen_blocks(self, t, xk, zk, xdot):
        """``E, G`` and index-check data at the start of a step."""
        return self.system.blocks(t, xdot, xk, zk, self.signal.at(t))

    def ift(self, times, inputs, h, xk, W, valid=None):
        """Attach implicit-function-theorem gradients to converged stages (see module doc).

        Samples outside ``valid`` (*batch,) (unconverged solves, discarded by the caller) get
        zero derivatives instead of a solve with a possibly singular matrix.
        """
        Wd = torch.nan_to_num(W.detach())
        if self.needs_grad is False or not torch.is_grad_enabled():
            return Wd
        with torch.enable_grad():
            R = self.residual(times, inputs, h, xk, Wd)
        # whether anything upstream requires grad cannot change during one integration
        self.needs_grad = R.requires_grad
        if not R.requires_grad:
            return Wd
        n, s, p = self.system.n, self.s, self.system.p
        K, Z = Wd[..., :n], Wd[..., n:]
        X = self.stage_states(xk.detach(), h, K)
        rows = []
        with torch.no_grad():
            for i in range(s):
                E_i, G_i, _, _ = self.system.blocks(
                    times[i], K[..., i, :], X[..., i, :], Z[..., i, :], inputs[i]
                )
                coupling = (
                    h[..., None, None, None] * self.A[i][:, None, None] * G_i[..., None, :, :]
                )
                row = (
                    coupling
                    + torch.eye(s, dtype=h.dtype, device=h.device)[i][:, None, None]
                    * E_i[..., None, :, :]
                )
                rows.append(row.movedim(-3, -2).reshape(*h.shape, p, s * p))
            J = torch.cat(rows, dim=-2)
            if valid is not None:
                eye = torch.eye(s * p, dtype=J.dtype, device=J.device)
                J = torch.where(valid[..., None, None], J, eye)
            lu, piv = torch.linalg.lu_factor(J)
        R = R.reshape(*h.shape, s * p, 1)
        if valid is not None:
            R = torch.where(valid[..., None, None], R, torch.zeros_like(R))
        D = -FrozenLUSolve.apply(lu, piv, R).reshape(Wd.shape)
        return Wd + (D - D.detach())


class IterationMatrix:
    """Per-sample frozen derivative blocks ``E, G`` and the LU factors of the Newton matrix.

    Jacobians and factorisations are computed for the whole batch when any sample needs them
    but adopted only by the samples that asked (``torch.where``), so a sample's numbers never
    depend on the other members of the batch.
    """

    def __init__(self, core: IRKCore, index_tol: float):
        self.core = core
        self.index_tol = index_tol
        self.E = self.G = self.factors = None
        self.n_jac = 0
        self.n_lu = 0

    def update_jacobian(self, mask, t, x, z, xdot):
        """Re-evaluate ``E, G`` at ``(t, x, z, xdot)`` for ``mask`` samples.

        Returns:
            (*batch,) bool: samples whose index-check matrix is numerically rank deficient.
        """
        with torch.no_grad():
            E, G, index_matrix, reference = self.core.frozen_blocks(t, x, z, xdot)
        self.n_jac += 1
        m3 = mask[..., None, None]
        self.E = E if self.E is None else torch.where(m3, E, self.E)
        self.G = G if self.G is None else torch.where(m3, G, self.G)
        if index_matrix is None:
            return torch.zeros_like(mask)
        return mask & (rank_ratio(index_matrix, reference) <= self.index_tol)

    def update_factors(self, mask, h):
        """Factorise the Newton matrix with step ``h`` (*batch,) for ``mask`` samples.

        Returns:
            (*batch,) bool: samples whose matrix is singular.
        """
        factors, singular = self.core.solver.factorize(self.E, self.G, h)
        self.n_lu += 1
        if self.factors is None:
            self.factors = factors
        else:
            self.factors = tuple(
                new
                if not isinstance(new, torch.Tensor)
                else torch.where(_expand_mask(mask, new), new, old)
                for new, old in zip(factors, self.factors, strict=True)
            )
        return mask & singular


def _expand_mask(mask, like):
    return mask.reshape(*mask.shape, *([1] * (like.dim() - mask.dim())))
