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
A second such correction, evaluated at that first-order-exact ``W``, makes second derivatives
exact as well (:meth:`IRKCore.ift`). Nothing of the Newton iterations is stored.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from ._irk_linalg import StageLinearSolver
from ._irk_system import StageSystem, jacobian_scale, rank_ratio
from .newton import newton, root_with_derivatives

EPS = {
    torch.float64: float(np.finfo(np.float64).eps),
    torch.float32: float(np.finfo(np.float32).eps),
}


class StageTimes:
    """The stage times ``t_k + c_i h`` of one step.

    ``times[i]`` is stage ``i``'s time, shaped like ``t_k`` (0-dim for a shared time,
    (*batch, 1) per sample); ``stacked`` holds all of them as (s, 1.., 1) / (s, *batch, 1) for
    one call with the stage index as leading batch dimension. Both are built on first use.
    """

    def __init__(self, c: list, tk: torch.Tensor, h: torch.Tensor, batch_ndim: int, stacked=None):
        self.c, self.tk, self.h, self.batch_ndim = c, tk, h, batch_ndim
        self._per_stage, self._stacked = None, stacked

    def __getitem__(self, i):
        if self._per_stage is None:
            self._per_stage = [self.tk + ci * self.h for ci in self.c]
        return self._per_stage[i]

    def __iter__(self):
        return iter([self[i] for i in range(len(self.c))])

    def __len__(self):
        return len(self.c)

    @property
    def stacked(self) -> torch.Tensor:
        if self._stacked is None:
            tk, h = self.tk, self.h
            shape = (len(self.c),) + (1,) * (self.batch_ndim + 1)
            c = torch.as_tensor(self.c, dtype=h.dtype, device=h.device).reshape(shape)
            self._stacked = tk + c * h
        return self._stacked


class StageInputs(list):
    """The inputs ``u(t_k + c_i h)`` of one step's stages (a list, None entries without an
    input); ``stacked`` holds them as one (s, 1.., *batch', nu) tensor, singleton batch
    dimensions inserted so that it broadcasts like the stacked stage states (s, *batch, n),
    or None without an input. Built on first use in each autograd mode: the copy built in
    the Newton iterations (no graph) would cut the gradients to the inputs from the
    implicit-function-theorem residual."""

    def __init__(self, inputs: list, batch_ndim: int):
        super().__init__(inputs)
        self.batch_ndim = batch_ndim
        self._stacked = {}  # torch.is_grad_enabled() -> stacked inputs

    @property
    def stacked(self) -> torch.Tensor | None:
        if self[0] is None:
            return None
        grad = torch.is_grad_enabled()
        if grad not in self._stacked:
            u = torch.stack(torch.broadcast_tensors(*self))  # (s, *batch', nu)
            missing = max(self.batch_ndim - (u.dim() - 2), 0)
            self._stacked[grad] = u.reshape(u.shape[0], *(1,) * missing, *u.shape[1:])
        return self._stacked[grad]


def stacked_call_agrees(by_stage: Callable, stacked: Callable, *values: torch.Tensor) -> bool:
    """Whether ``stacked(*values)``, one call of the user's functions with the stage index as
    leading batch dimension, reproduces ``by_stage(*values)``, one call per stage (both
    (*batch, s, p) from stage values (*batch, s, .)), to ``1000 eps``. Checked at ``values``
    perturbed differently in every entry, so that a function mixing up the batch and stage
    dimensions is caught; a function that raises there is evaluated stage by stage (at the
    real stage values, where its own errors surface)."""

    def perturb(v):
        pattern = torch.linspace(0.1, 0.2, v.numel(), dtype=v.dtype, device=v.device)
        pattern = pattern.reshape(v.shape)
        return v * (1 + 1e-3 * pattern) + 1e-3 * pattern

    with torch.no_grad():
        perturbed = [perturb(v) for v in values]
        try:
            ref, got = by_stage(*perturbed), stacked(*perturbed)
        except Exception:  # noqa: BLE001 - any failure means "not stackable"
            return False
    if got.shape != ref.shape:
        return False
    tol = 1e3 * EPS.get(ref.dtype, EPS[torch.float32])
    return bool(torch.allclose(got, ref, rtol=tol, atol=tol, equal_nan=True))


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
    """Stage inputs read from a ``BoundRHS`` (:mod:`integrators.inputs`), or none.

    Args:
        source: None or a bound rhs with ``kind`` / ``u`` / ``input_at`` (``bind_rhs``).
    """

    def __init__(self, source):
        self.source = source

    def at(self, t, t_step=None):
        """Input at time ``t``; a zero-order-hold signal holds ``u(t_step)`` over the closed
        step from ``t_step`` (eq. 8.34), so a stage with ``c_i = 1`` still sees ``u_k``: fixed
        steps lie within a sample interval, and adaptive steps end at the sample times
        (:attr:`integrators.inputs.BoundRHS.breakpoints`)."""
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
        self.stack_stages = None
        self._hA_key = self._hA = None
        self._rms_scale = 1.0 / (self.s * system.p) ** 0.5
        # (A (x) I_n)^T: ``K.flatten(-2) @ _A_kron_T`` is ``A @ K`` flattened, one plain matrix
        # product for the whole batch instead of a batched product of tiny matrices
        eye_n = torch.eye(system.n, dtype=dtype, device=device)
        self._A_kron_T = torch.kron(self.A, eye_n).T.contiguous()

    # ------------------------------------------------------------------ stages
    def stage_times(self, tk, h, batch_ndim: int, stacked=None):
        """Stage times ``t_k + c_i h`` (:class:`StageTimes`); ``tk``/``h`` 0-dim (shared) or
        (*batch, 1) with ``len(batch) = batch_ndim``; ``stacked`` (s, *batch, 1) when the
        caller already has them."""
        return StageTimes(self.c, tk, h, batch_ndim, stacked)

    def stage_inputs(self, times, tk) -> StageInputs:
        """The stage inputs (:class:`StageInputs`) at the stage times ``times`` of the step from
        ``tk``; a zero-order-hold input holds ``u(t_k)`` (``InputSignal.at``)."""
        if self.signal.source is None or self.signal.source.kind == "none":
            return StageInputs([None] * self.s, times.batch_ndim)
        return StageInputs([self.signal.at(ti, tk) for ti in times], times.batch_ndim)

    def stage_states(self, xk, h, K):
        """``X_i = x_k + h sum_j a_ij K_j``: (*batch, s, n); h is (*batch,)."""
        return xk[..., None, :] + self._step_matrix(h) @ K

    def _apply_A(self, K):
        """``A @ K`` (*batch, s, n) as one flat matrix product (see ``_A_kron_T``)."""
        return (K.reshape(*K.shape[:-2], -1) @ self._A_kron_T).reshape(K.shape)

    def _step_matrix(self, h):
        """``h A`` (*batch, s, s), cached for the step-size tensor ``h`` of the current step."""
        if self._hA_key is not h:
            self._hA_key, self._hA = h, h[..., None, None] * self.A
        return self._hA

    def residual(self, times, inputs, h, xk, W):
        """Stage residuals (*batch, s, p) of the stage unknowns ``W`` (*batch, s, p).

        When the problem's functions accept a leading extra batch dimension (tested once, see
        :meth:`stacking_works`), all stages are evaluated in one call with the stage index as
        leading batch dimension of the times, states and inputs (``inputs.stacked``);
        otherwise stage by stage.
        """
        n = self.system.n
        K = W[..., :n] if self.system.m else W
        self.n_f_evals += self.s
        if self.stack_stages is None:
            X = self.stage_states(xk, h, K)
            self.stack_stages = self.stacking_works(times, inputs, K, X, W[..., n:])
        if self.stack_stages:
            Xs = torch.addcmul(xk, h[..., None], self._apply_A(K).movedim(-2, 0))
            if self.system.kind == "ode":  # K - f(t, X) (eq. 7.14), laid out like K
                return K - self.system.rhs_f(times.stacked, Xs, None, inputs.stacked).movedim(0, -2)
            Zs = W[..., n:].movedim(-2, 0)
            R = self.system.residual(times.stacked, K.movedim(-2, 0), Xs, Zs, inputs.stacked)
            return R.movedim(0, -2)
        X = self.stage_states(xk, h, K)
        return self._residual_by_stage(times, inputs, K, X, W[..., n:])

    def _residual_by_stage(self, times, inputs, K, X, Z):
        return torch.stack(
            [
                self.system.residual(times[i], K[..., i, :], X[..., i, :], Z[..., i, :], inputs[i])
                for i in range(self.s)
            ],
            dim=-2,
        )

    def stacking_works(self, times, inputs, K, X, Z) -> bool:
        """Whether one call with stacked stages (s, *batch, .) reproduces the stage-by-stage
        residuals (:func:`stacked_call_agrees`, near the first stage values)."""

        def stacked(K, X, Z):
            R = self.system.residual(
                times.stacked, K.movedim(-2, 0), X.movedim(-2, 0), Z.movedim(-2, 0), inputs.stacked
            )
            return R.movedim(0, -2)

        return stacked_call_agrees(
            lambda K, X, Z: self._residual_by_stage(times, inputs, K, X, Z), stacked, K, X, Z
        )

    def step_end(self, xk, h, W):
        """``x_{k+1} = x_k + h sum_i b_i K_i`` (eq. 7.18): (*batch, n)."""
        K = W[..., : self.system.n] if self.system.m else W
        return xk + h[..., None] * (self.b @ K)

    # ------------------------------------------------------------------ Newton
    def _weighted_norm(self, dW, w_x, w_z):
        """``||[(A dK) w_x, dZ w_z]||_2`` (*batch,) for weights ``w_x = h / sc_x``
        (*batch, 1, n) and ``w_z = 1 / sc_z`` (*batch, 1, m); times ``_rms_scale`` it is the
        RMS of the scaled state increments ``h A dK / sc_x`` and ``dZ / sc_z``."""
        n = self.system.n
        dK = dW[..., :n] if self.system.m else dW
        q = torch.linalg.vector_norm(self._apply_A(dK) * w_x, dim=(-2, -1))
        if self.system.m:
            q = torch.hypot(q, torch.linalg.vector_norm(dW[..., n:] * w_z, dim=(-2, -1)))
        return q

    @torch.no_grad()
    def newton(
        self, times, inputs, h, xk, W, factors, sc_x, sc_z, tol, max_iter, active, predict=True
    ):
        """Simplified Newton on the stage equations, per sample.

        Convergence needs a measured contraction rate ``theta`` (two iterations, as in
        scipy's Radau) unless the update is exactly zero: ``theta / (1 - theta) ||dW|| <= tol``.
        A member stops as failed when ``theta >= 1`` or (``predict=True``, used where a
        smaller step is the remedy) when the rate predicts that ``max_iter`` iterations will
        not reach ``tol``. The per-sample bookkeeping runs on the host (numpy): one transfer
        of the (*batch,) increment norms per iteration.

        Args:
            times, inputs: stage times and inputs.
            h: (*batch,) step sizes; xk (*batch, n); W (*batch, s, p) initial guess.
            factors: from ``StageLinearSolver.factorize``.
            sc_x, sc_z: (*batch, n), (*batch, m) error scales ``atol + rtol |.|``.
            tol: convergence tolerance in the scaled norm.
            max_iter: iteration limit.
            active: (*batch,) numpy bool: samples to solve (others are left untouched).

        Returns:
            ``(W, converged, iterations, theta, non_finite)``: W a tensor without autograd
            graph (gradients come from :meth:`ift`), the others (*batch,) numpy arrays.
        """
        w_x = (h[..., None] / sc_x)[..., None, :]
        w_z = (1.0 / sc_z)[..., None, :] if self.system.m else None
        live = active.copy()  # still iterating
        conv = np.zeros_like(live)
        non_finite = np.zeros_like(live)
        iters = np.zeros(live.shape, dtype=np.int64)
        theta = np.zeros(live.shape)
        tiny = torch.finfo(h.dtype).tiny
        norm_old = None
        with np.errstate(all="ignore"):
            for it in range(max_iter):
                R = self.residual(times, inputs, h, xk, W)
                dW = self.solver.solve(factors, R, h)
                norm = to_host(self._weighted_norm(dW, w_x, w_z), live.shape)
                norm = norm.astype(np.float64, copy=False) * self._rms_scale
                finite = np.isfinite(norm)
                if not finite.all():
                    bad = live & ~finite
                    non_finite |= bad
                    live &= ~bad
                if norm_old is None:
                    done = live & (norm == 0)
                else:
                    th = norm / np.maximum(norm_old, tiny)
                    np.copyto(theta, th, where=live)
                    gap = 1.0 - th
                    hopeless = th >= 1.0
                    if predict:
                        hopeless |= th ** (max_iter - it) / np.maximum(gap, 1e-12) * norm > tol
                    live &= ~hopeless
                    done = live & ((norm == 0) | (th / gap * norm <= tol))
                W = masked_update(live, W + dW, W)
                iters += live
                conv |= done
                live &= ~done
                norm_old = norm
                if not live.any():
                    break
        return W, conv, iters, theta, non_finite

    def damped_newton(self, times, inputs, h, xk, W, active, tol, max_iter=50):
        """Fallback for a fixed step whose simplified Newton failed (a fixed step cannot be
        shortened): damped Newton with the exact stage Jacobian at every iterate (notes
        Theorem 4) on the flattened stage residual.

        Args:
            h (*batch,), xk (*batch, n), W (*batch, s, p): as in :meth:`newton`.
            active: (*batch,) numpy bool: the members to solve.
            tol: residual tolerance ``||R||_inf`` (derivative units).

        Returns:
            ``(W, converged, iterations)`` (the last two host arrays); members outside
            ``active`` keep ``W`` and report zero iterations. No autograd graph (gradients
            come from :meth:`ift`).
        """
        stage_shape = W.shape[-2:]

        def phi(w):
            return self.residual(times, inputs, h, xk, w.unflatten(-1, stage_shape)).flatten(-2)

        with torch.no_grad():
            res = newton(phi, W.detach().flatten(-2), method="damped", tol=tol, max_iter=max_iter)
        converged = to_host(res.converged, active.shape) & active
        W_new = masked_update(active, res.x.detach().unflatten(-1, stage_shape), W)
        return W_new, converged, to_host(res.iterations, active.shape) * active

    # --------------------------------------------------------------- Jacobians
    def frozen_blocks(self, t, xk, zk, xdot):
        """``E, G`` and index-check data at the start of a step."""
        return self.system.blocks(t, xdot, xk, zk, self.signal.at(t))

    def ift(self, times, inputs, h, xk, W, valid=None):
        """Attach implicit-function-theorem gradients to converged stages (see module doc).

        Two zero-valued Newton corrections with the exact stage Jacobian ``J`` at ``W*``
        (frozen, :func:`root_with_derivatives`) carry the first and second derivatives with
        respect to ``x_k`` and every tensor the model uses, so Hessians and Hessian-vector
        products (``create_graph``) are those of the discrete solution, not only gradients.

        Samples outside ``valid`` ((*batch,) numpy bool: unconverged solves, discarded by the
        caller) get zero derivatives instead of a solve with a possibly singular matrix.
        """
        Wd = torch.nan_to_num(W.detach())
        if not torch.is_grad_enabled():
            return Wd
        with torch.enable_grad():
            R = self.residual(times, inputs, h, xk, Wd)
        # decided per step: a model may read a tensor that requires grad only in some steps
        # (a branch on t or x), so a step without one says nothing of the next
        if not R.requires_grad:
            return Wd
        n, s, p = self.system.n, self.s, self.system.p
        if valid is not None:
            valid = None if valid.all() else to_device(valid, h, shape=h.shape)
        K, Z = Wd[..., :n], Wd[..., n:]
        X = self.stage_states(xk.detach(), h, K)
        with torch.no_grad():
            if self.stack_stages:
                E, G, _, _ = self.system.blocks(
                    times.stacked,
                    K.movedim(-2, 0),
                    X.movedim(-2, 0),
                    Z.movedim(-2, 0),
                    inputs.stacked,
                )
            else:
                pairs = [
                    self.system.blocks(times[i], K[..., i, :], X[..., i, :], Z[..., i, :], u)[:2]
                    for i, u in enumerate(inputs)
                ]
                E, G = (torch.stack(v) for v in zip(*pairs, strict=True))
            # J[(i, a), (j, c)] = delta_ij E_i[a, c] + h a_ij G_i[a, c]  (E_i, G_i at stage i)
            E, G = E.movedim(0, -3)[..., :, :, None, :], G.movedim(0, -3)[..., :, :, None, :]
            eye_s = torch.eye(s, dtype=h.dtype, device=h.device)[:, None, :, None]
            hA = h[..., None, None, None, None] * self.A[:, None, :, None]
            J = (eye_s * E + hA * G).reshape(*h.shape, s * p, s * p)
            if valid is not None:
                eye = torch.eye(s * p, dtype=J.dtype, device=J.device)
                J = torch.where(valid[..., None, None], J, eye)
            lu, piv = torch.linalg.lu_factor(J)

        def flat(R):
            R = R.reshape(*h.shape, s * p)
            return R if valid is None else torch.where(valid[..., None], R, 0.0)

        def residual(Wf):
            return flat(self.residual(times, inputs, h, xk, Wf.unflatten(-1, (s, p))))

        def solve(r):
            return FrozenLUSolve.apply(lu, piv, r[..., None])[..., 0]

        W_root = root_with_derivatives(residual, Wd.flatten(-2), solve, r_star=flat(R))
        return W_root.unflatten(-1, (s, p))


def host_shape(batch) -> tuple:
    """Shape of the host (numpy) per-sample arrays: the batch shape, (1,) for an unbatched
    state (numpy turns 0-d results into scalars, which cannot be updated in place)."""
    return tuple(batch) if len(batch) else (1,)


def to_host(x: torch.Tensor, shape=None) -> np.ndarray:
    """A detached host (numpy) copy of ``x`` (reshaped to ``shape``): the one device-to-host
    transfer of a check."""
    out = np.array(x.numpy(force=True))
    return out if shape is None else out.reshape(shape)


def to_device(a: np.ndarray, like: torch.Tensor, dtype=None, shape=None) -> torch.Tensor:
    """Host array ``a`` as a tensor on ``like``'s device (``dtype`` default: ``a``'s),
    reshaped to ``shape``."""
    out = torch.from_numpy(np.ascontiguousarray(a))
    if like.device.type != "cpu" or (dtype is not None and dtype != out.dtype):
        out = out.to(device=like.device, dtype=dtype)
    return out if shape is None else out.reshape(shape)


def masked_update(mask: np.ndarray, new: torch.Tensor, old: torch.Tensor) -> torch.Tensor:
    """``new`` where the host bool ``mask`` (*batch,) holds, else ``old``; no op when the mask
    is uniform (the common case: every member moves together)."""
    if mask.all():
        return new
    if not mask.any():
        return old
    expand = mask.reshape(*mask.shape, *([1] * (new.dim() - mask.ndim)))
    return torch.where(to_device(expand, new), new, old)


class IterationMatrix:
    """Per-sample frozen derivative blocks ``E, G`` and the LU factors of the Newton matrix.

    Jacobians and factorisations are computed for the whole batch when any sample needs them
    but adopted only by the samples that asked (``torch.where``), so a sample's numbers never
    depend on the other members of the batch.
    """

    def __init__(self, core: IRKCore, index_tol: float):
        self.core = core
        self.index_tol = index_tol
        self.E = self.G = self.factors = self.parts = None
        self.scale0 = None  # (*batch,) Jacobian norm at the start: caps the rank test's scale
        self.n_jac = 0
        self.n_lu = 0

    def update_jacobian(self, mask, t, x, z, xdot):
        """Re-evaluate ``E, G`` at ``(t, x, z, xdot)`` for the host bool ``mask`` samples.

        Returns:
            (*batch,) numpy bool: samples whose index-check matrix is numerically rank
            deficient at finite values (:func:`rank_ratio`, its scale capped by the
            Jacobian's norm at the first evaluation, the start of the integration).
        """
        with torch.no_grad():
            E, G, index_matrix, reference = self.core.frozen_blocks(t, x, z, xdot)
        self.n_jac += 1
        identity_E = self.core.system.kind == "ode"  # dR/dK = I for explicit ODEs
        if self.E is None or not identity_E:
            self.E = E if self.E is None else masked_update(mask, E, self.E)
        self.G = G if self.G is None else masked_update(mask, G, self.G)
        self.parts = self.core.solver.prepare(None if identity_E else self.E, self.G)
        if index_matrix is None:
            return np.zeros_like(mask)
        if self.scale0 is None:  # the first evaluation is at the (consistent) start
            self.scale0 = jacobian_scale(reference)
        ratio = rank_ratio(index_matrix, reference, self.scale0)
        return mask & (to_host(ratio, mask.shape) <= self.index_tol)

    def update_factors(self, mask, h):
        """Factorise the Newton matrix with step ``h`` (*batch,) for the host bool ``mask``
        samples.

        Returns:
            (*batch,) numpy bool: samples whose matrix is singular.
        """
        factors, singular = self.core.solver.factorize(self.E, self.G, h, self.parts)
        self.n_lu += 1
        if self.factors is None or self.factors[0] != factors[0]:
            self.factors = factors
        else:
            self.factors = tuple(
                masked_update(mask, new, old) if isinstance(new, torch.Tensor) else new
                for new, old in zip(factors, self.factors, strict=True)
            )
        return mask & to_host(singular, mask.shape)
