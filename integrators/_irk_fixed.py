"""Fixed-step implicit Runge-Kutta integration (notes §7.2, algorithm "IRK for explicit ODEs",
and its implicit-ODE / DAE variants eq. 7.51-7.60).

Every output interval ``[t_k, t_{k+1}]`` is split into ``substeps`` equal steps. The Newton
matrix is reused from step to step while the previous stage solve converged in two iterations
or contracted fast (``theta <= 1e-3``; scipy's rule, as in the adaptive driver: a rate measured
in a two-iteration solve is round-off over round-off when the stage guess was already exact,
e.g. on a linear problem) and the step size is unchanged (steps equal to rounding, as on a
uniform grid, count as equal); a slow or failed solve re-evaluates the Jacobian at the current
state and a failed solve with a fresh Jacobian marks the sample NEWTON_FAILED (its state is
then held and its outputs after the start of the failed step are NaN). Per-sample flags and
counters are host (numpy) arrays, so the only device-to-host transfers are one per Newton
iteration (the increment norms).
"""

from __future__ import annotations

import warnings

import numpy as np
import torch

from ._irk_core import IRKCore, IterationMatrix, host_shape, masked_update, to_host
from ._irk_dense import (
    StepRecords,
    extrapolation_matrix,
    is_collocation,
    nan_beyond,
    stop_times,
)
from .collocation import lagrange_basis
from .controllers import REUSE_THETA, slow_contraction
from .errors import HighIndexWarning
from .solution import Status


def _endpoint_stage(core: IRKCore) -> bool:
    """Whether the last stage sits at the step's end (``c_s = 1``, e.g. Radau IIA)."""
    return abs(core.c[-1] - 1.0) < 1e-14


def end_algebraic(core: IRKCore, W, z):
    """``z_{k+1}``: the last algebraic stage when ``c_s = 1``, else its polynomial at 1 (a
    lower order than the differential states': the output times solve for ``z`` again, see
    :func:`integrate_fixed`)."""
    n = core.system.n
    if core.system.m == 0:
        return z
    if _endpoint_stage(core):
        return W[..., -1, n:]
    c = torch.as_tensor(core.c, dtype=W.dtype, device=W.device)
    basis = lagrange_basis(c, torch.ones((), dtype=W.dtype, device=W.device))
    return torch.einsum("s,...sm->...m", basis, W[..., n:])


def integrate_fixed(
    core: IRKCore,
    x0,
    z0,
    xdot0,
    t,
    *,
    substeps,
    rtol,
    atol,
    max_iter,
    newton_tol,
    index_tol,
    index_check_every=10,
):
    """Run the fixed-step method; returns a dict of outputs, status, counters and messages.

    A DAE's algebraic states at the output times: with ``c_s = 1`` (Radau IIA, implicit
    Euler) the last stage's, of the order of the differential states; otherwise (Gauss-
    Legendre, implicit midpoint) the stage polynomial extrapolated to the step's end is of
    lower order and leaves ``g(x, z) != 0``, so ``z`` is solved from the algebraic equations
    at ``x(t_{k+1})`` there (:meth:`StageSystem.algebraic_states`, held input of the last
    step); a sample where that Newton solve fails stops with ``NEWTON_FAILED``."""
    batch = x0.shape[:-1]
    hshape = host_shape(batch)
    status = np.zeros(hshape, dtype=np.int8)
    active = np.ones(hshape, dtype=bool)
    t_stop = np.zeros(hshape)  # start of the step where a sample stopped
    n_newton = np.zeros(hshape, dtype=np.int64)
    n_steps = np.zeros(hshape, dtype=np.int64)
    messages: list[str] = []
    mat = IterationMatrix(core, index_tol)
    records = StepRecords(core.tab, core.system.n) if is_collocation(core.tab) else None
    x, z, xdot = x0, z0, xdot0
    xs, zs = [x0], [z0]
    need_jac = np.ones(hshape, dtype=bool)
    fresh = np.zeros(hshape, dtype=bool)
    h_fact = h_prev = None
    prev_W = None
    guess = _StageExtrapolation(core, x0)
    t_host = to_host(t).astype(np.float64)
    # every step's size, start time and stage times, computed for the whole grid at once
    steps = (t[1:] - t[:-1]) / substeps  # (K,)
    starts = t[:-1, None] + torch.arange(substeps, dtype=t.dtype, device=t.device) * steps[:, None]
    c = torch.as_tensor(core.c, dtype=t.dtype, device=t.device)
    stage_grid = (starts[..., None] + c * steps[:, None, None]).reshape(
        *starts.shape, core.s, *([1] * (len(batch) + 1))
    )
    for k in range(t.shape[0] - 1):
        h = steps[k]
        h_val = float((t_host[k + 1] - t_host[k]) / substeps)
        hb = h.expand(batch)
        for j in range(substeps):
            tk = starts[k, j]
            t_stop = np.where(active, t_host[k] + j * h_val, t_stop)
            times = core.stage_times(tk, h, len(batch), stacked=stage_grid[k, j])
            inputs = core.stage_inputs(times, tk)
            xd, zd = x.detach(), z.detach()
            sc_x = atol + rtol * xd.abs()
            sc_z = atol + rtol * zd.abs() if core.system.m else zd
            W0 = guess(prev_W, 1.0 if h_prev is None else _ratio(h_val, h_prev), xdot.detach(), zd)
            h_prev = h_val
            W_ok = W0
            conv_all = np.zeros_like(active)
            theta_all = np.zeros(hshape)
            iters_all = np.zeros(hshape, dtype=np.int64)
            todo = active.copy()
            for attempt in range(2):
                if attempt == 1:  # a stale Jacobian failed: refresh it and retry those samples
                    todo = active & ~conv_all & ~fresh
                    if not todo.any():
                        break
                    need_jac = todo
                refactor = need_jac.copy()
                if need_jac.any():
                    high = mat.update_jacobian(need_jac, tk, xd, zd, xdot.detach())
                    fresh |= need_jac
                    _flag_high_index(high & active, status, active, messages, tk)
                if h_fact is None or _ratio(h_val, h_fact) != 1.0:
                    refactor |= active
                    h_fact = h_val
                if refactor.any():
                    mat.update_factors(refactor, hb)
                W, converged, iters, theta, _ = core.newton(
                    times,
                    inputs,
                    hb,
                    xd,
                    W0,
                    mat.factors,
                    sc_x,
                    sc_z,
                    newton_tol,
                    max_iter,
                    todo & active,
                    predict=False,
                )
                n_newton += iters
                W_ok = masked_update(todo, W, W_ok)
                conv_all |= converged
                theta_all = np.where(todo, theta, theta_all)
                iters_all = np.where(todo, iters, iters_all)
            simplified_ok = conv_all.copy()
            failed = active & ~conv_all
            if failed.any():  # last resort: damped Newton with exact Jacobians
                residual_tol = newton_tol * float(sc_x.min()) / h_val
                W_fb, rescued, iters = core.damped_newton(
                    times, inputs, hb, xd, W_ok, failed, residual_tol
                )
                n_newton += iters
                W_ok = masked_update(rescued, W_fb, W_ok)
                conv_all |= rescued
                failed = active & ~conv_all
            if failed.any():
                for idx in np.argwhere(failed).tolist():
                    messages.append(
                        f"sample {tuple(idx)}: the implicit stage equations did not converge at "
                        f"t = {float(tk):.6g} (step {k}, substep {j}, dt = {h_val:.3g}); try "
                        "more substeps, an adaptive method or a better-scaled model; its "
                        f"outputs after t = {float(tk):.6g} are NaN."
                    )
                status[failed] = int(Status.NEWTON_FAILED)
                active &= ~failed
            W = core.ift(times, inputs, hb, x, W_ok, valid=active)
            x_new = core.step_end(x, hb, W)
            z_new = end_algebraic(core, W, z)
            if records is not None:
                records.append(
                    np.full(batch, t_host[k] + j * h_val), np.full(batch, h_val), x, W, z
                )
            x = masked_update(active, x_new, x)
            z = masked_update(active, z_new, z)
            xdot = masked_update(active, W[..., -1, : core.system.n].detach(), xdot)
            n_steps += active
            fresh = np.zeros_like(fresh)
            # scipy's rule, and a slow simplified Newton that failed
            slow = slow_contraction(theta_all, iters_all) | (
                (theta_all > REUSE_THETA) & ~simplified_ok
            )
            need_jac = active & slow
            if core.system.kind != "ode":  # periodic index check (Theorem 9)
                need_jac |= active & (n_steps % index_check_every == 0)
            prev_W = W.detach()
        if core.system.m and not _endpoint_stage(core):
            was_active = active.copy()
            z = _consistent_end(core, mat, t[k + 1], x, z, xdot, tk, active, status, messages)
            t_stop = np.where(was_active & ~active, t_host[k + 1], t_stop)  # x is valid there
        xs.append(x)
        zs.append(z)

    def dev(a):
        return torch.from_numpy(a).to(x0.device).reshape(batch)

    stop = stop_times(status, t_stop)
    if records is not None:
        records.stop = stop
    return dict(
        x=nan_beyond(torch.stack(xs, dim=-2), t, stop),
        z=nan_beyond(torch.stack(zs, dim=-2), t, stop),
        status=dev(status),
        messages=messages,
        n_steps=dev(n_steps),
        n_newton=dev(n_newton),
        n_jac=mat.n_jac,
        n_lu=mat.n_lu,
        n_f=core.n_f_evals,
        records=records,
    )


def _consistent_end(core: IRKCore, mat, t_end, x, z, xdot, tk, active, status, messages):
    """``z`` solved from the algebraic equations at ``(t_end, x)`` from the guesses ``z`` (and
    ``xdot`` for an implicit DAE), with the input held from the last step's start ``tk``. The
    ``active`` samples whose Newton solve fails stop (``status``, ``messages``, in place) and
    keep the guess: as of index > 1 where the index test (``mat``, Theorem 9) says so."""
    u = core.signal.at(t_end, tk)
    _, z_new, res = core.system.algebraic_states(t_end, x, z, u, xdot)
    failed = active & ~to_host(res.converged, active.shape)
    if failed.any():
        high = mat.update_jacobian(failed, t_end, x.detach(), z.detach(), xdot.detach())
        _flag_high_index(high & failed, status, active, messages, t_end)
        failed &= ~high
    for idx in np.argwhere(failed).tolist():
        messages.append(
            f"sample {tuple(idx)}: the algebraic equations did not converge for z at the "
            f"output time t = {float(t_end):.6g}; its outputs from there on are NaN."
        )
    status[failed] = int(Status.NEWTON_FAILED)
    active &= ~failed
    return masked_update(active, z_new, z)


def _ratio(h_new: float, h_old: float) -> float:
    """``h_new / h_old``, snapped to 1 when the steps agree to rounding (the steps of a uniform
    grid differ in the last bits): the factorisation and the extrapolation matrix are reused.
    """
    ratio = h_new / h_old
    return 1.0 if abs(ratio - 1.0) <= 1e-12 else ratio


class _StageExtrapolation:
    """Starting stages of a fixed step: the previous stage polynomial extrapolated by the
    step ratio (the Lagrange matrix of the last ratio is kept), else constant ``(x', z)``."""

    def __init__(self, core: IRKCore, like: torch.Tensor):
        self.s = core.s
        self.c = np.array(core.c)
        self.like = like
        self.ratio, self.L = None, None

    def __call__(self, prev_W, ratio: float, xdot, z):
        if prev_W is None:
            const = torch.cat([xdot, z], dim=-1)[..., None, :]
            return const.expand(*xdot.shape[:-1], self.s, const.shape[-1])
        if ratio != self.ratio:
            L = extrapolation_matrix(self.c, ratio)
            self.ratio = ratio
            self.L = torch.as_tensor(L, dtype=self.like.dtype, device=self.like.device)
        return self.L @ prev_W


def _flag_high_index(high, status, active, messages, t):
    """Warn and stop samples whose algebraic Jacobian became rank deficient (Theorem 9).

    ``high``, ``status``, ``active`` are host (numpy) arrays (the last two updated in place);
    ``t`` the time of the check: shared (0-dim tensor, fixed steps) or per sample (host array
    of ``high``'s shape, adaptive steps). One message per distinct time, naming the samples
    flagged at it.
    """
    if not high.any():
        return
    t_host = np.asarray(t.detach().cpu() if isinstance(t, torch.Tensor) else t, dtype=np.float64)
    if t_host.size == high.size:  # per-sample times: each sample's own
        t_host = t_host.reshape(high.shape)
    times = np.broadcast_to(t_host if t_host.shape == high.shape else t_host.flat[0], high.shape)
    by_time: dict[float, list] = {}
    for i in np.argwhere(high).tolist():
        by_time.setdefault(float(times[tuple(i)]), []).append(tuple(i))
    for when, idx in by_time.items():
        msg = (
            f"the DAE's algebraic Jacobian (dg/dz, or [dF/dx' dF/dz]) became rank deficient at "
            f"t = {when:.6g} for samples {idx[:10]}: the DAE is of index > 1 "
            "there (Theorem 9, Corollary 1) and implicit RK results would be meaningless; "
            "index-reduce the model (notes §5.4, §7.6.1). Their outputs after this time are NaN."
        )
        warnings.warn(msg, HighIndexWarning, stacklevel=4)
        messages.append(msg)
    status[high] = int(Status.NEWTON_FAILED)
    active[high] = False
