"""Fixed-step implicit Runge-Kutta integration (notes §7.2, algorithm "IRK for explicit ODEs",
and its implicit-ODE / DAE variants eq. 7.51-7.60).

Every output interval ``[t_k, t_{k+1}]`` is split into ``substeps`` equal steps. The Newton
matrix is reused from step to step while the previous stage solve contracted fast
(``theta <= 1e-3``); a slow or failed solve re-evaluates the Jacobian at the current state and
a failed solve with a fresh Jacobian marks the sample NEWTON_FAILED (its state is then held).
"""

from __future__ import annotations

import warnings

import torch

from ._irk_core import IRKCore, IterationMatrix
from ._irk_dense import StepRecords, extrapolate_stages, is_collocation, lagrange_basis
from .errors import HighIndexWarning
from .solution import Status

_REUSE_THETA = 1e-3


def stage_guess(core: IRKCore, prev_W, ratio, xdot, z):
    """Starting stages: extrapolated previous polynomial, else constant ``(xdot, z)``."""
    if prev_W is not None:
        c = torch.as_tensor(core.c, dtype=xdot.dtype, device=xdot.device)
        return extrapolate_stages(c, prev_W, ratio)
    return torch.cat([xdot, z], dim=-1)[..., None, :].expand(*xdot.shape[:-1], core.s, -1)


def end_algebraic(core: IRKCore, W, z):
    """``z_{k+1}``: the last algebraic stage when ``c_s = 1``, else its polynomial at 1."""
    n = core.system.n
    if core.system.m == 0:
        return z
    if abs(core.c[-1] - 1.0) < 1e-14:
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
    """Run the fixed-step method; returns a dict of outputs, status, counters and messages."""
    batch = x0.shape[:-1]
    dev = x0.device
    status = torch.zeros(batch, dtype=torch.int8, device=dev)
    active = torch.ones(batch, dtype=torch.bool, device=dev)
    n_newton = torch.zeros(batch, dtype=torch.int64, device=dev)
    n_steps = torch.zeros(batch, dtype=torch.int64, device=dev)
    messages: list[str] = []
    mat = IterationMatrix(core, index_tol)
    records = StepRecords(core.tab, core.system.n) if is_collocation(core.tab) else None
    x, z, xdot = x0, z0, xdot0
    xs, zs = [x0], [z0]
    need_jac = torch.ones(batch, dtype=torch.bool, device=dev)
    fresh = torch.zeros(batch, dtype=torch.bool, device=dev)
    h_fact = None
    prev_W = None
    one = torch.ones(batch, dtype=x0.dtype, device=dev)
    for k in range(t.shape[0] - 1):
        h = (t[k + 1] - t[k]) / substeps
        hb = h.expand(batch)
        for j in range(substeps):
            tk = t[k] + j * h
            times = core.stage_times(tk, h)
            inputs = core.stage_inputs(times, tk, fixed=True)
            sc_x = atol + rtol * x.detach().abs()
            sc_z = atol + rtol * z.detach().abs()
            ratio = one if h_fact is None else one * (float(h) / h_fact)
            W0 = stage_guess(core, prev_W, ratio, xdot.detach(), z.detach())
            W_ok = W0
            conv_all = torch.zeros_like(active)
            theta_all = torch.zeros_like(one)
            todo = active
            for attempt in range(2):
                if attempt == 1:  # a stale Jacobian failed: refresh it and retry those samples
                    todo = active & ~conv_all & ~fresh
                    if not bool(todo.any()):
                        break
                    need_jac = todo
                refactor = need_jac.clone()
                if bool(need_jac.any()):
                    high = mat.update_jacobian(need_jac, tk, x.detach(), z.detach(), xdot.detach())
                    fresh = fresh | need_jac
                    _flag_high_index(high & active, status, active, messages, tk)
                if h_fact is None or float(h) != h_fact:
                    refactor = refactor | active
                    h_fact = float(h)
                if bool(refactor.any()):
                    mat.update_factors(refactor, hb)
                W, converged, iters, theta, _ = core.newton(
                    times,
                    inputs,
                    hb,
                    x.detach(),
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
                W_ok = torch.where(todo[..., None, None], W, W_ok)
                conv_all = conv_all | converged
                theta_all = torch.where(todo, theta, theta_all)
            failed = active & ~conv_all
            if bool(failed.any()):  # last resort: damped Newton with exact Jacobians
                residual_tol = newton_tol * float(sc_x.min()) / float(h)
                W_fb, rescued, iters = core.damped_newton(
                    times, inputs, hb, x.detach(), W_ok, failed, residual_tol
                )
                n_newton += iters
                W_ok = torch.where(rescued[..., None, None], W_fb, W_ok)
                conv_all = conv_all | rescued
                failed = active & ~conv_all
            if bool(failed.any()):
                for idx in torch.nonzero(failed).tolist():
                    messages.append(
                        f"sample {tuple(idx)}: the implicit stage equations did not converge at "
                        f"t = {float(tk):.6g} (step {k}, substep {j}, dt = {float(h):.3g}); try "
                        "more substeps, an adaptive method or a better-scaled model."
                    )
                status = torch.where(failed, torch.full_like(status, Status.NEWTON_FAILED), status)
                active = active & ~failed
            W = core.ift(times, inputs, hb, x, W_ok, valid=active)
            x_new = core.step_end(x, hb, W)
            z_new = end_algebraic(core, W, z)
            xdot_new = W[..., -1, : core.system.n].detach()
            if records is not None:
                records.append(tk.expand(batch), hb, x, W, z)
            a1 = active[..., None]
            x = torch.where(a1, x_new, x)
            z = torch.where(a1, z_new, z)
            xdot = torch.where(a1, xdot_new, xdot)
            n_steps += active.long()
            fresh = torch.zeros_like(fresh)
            need_jac = active & (theta_all > _REUSE_THETA)
            if core.system.kind != "ode":  # periodic index check (Theorem 9)
                need_jac = need_jac | (active & (n_steps % index_check_every == 0))
            prev_W = W.detach()
        xs.append(x)
        zs.append(z)
    return dict(
        x=torch.stack(xs, dim=-2),
        z=torch.stack(zs, dim=-2),
        status=status,
        messages=messages,
        n_steps=n_steps,
        n_newton=n_newton,
        n_jac=mat.n_jac,
        n_lu=mat.n_lu,
        n_f=core.n_f_evals,
        records=records,
    )


def _flag_high_index(high, status, active, messages, t):
    """Warn and stop samples whose algebraic Jacobian became rank deficient (Theorem 9)."""
    if not bool(high.any()):
        return
    idx = [tuple(i) for i in torch.nonzero(high).tolist()]
    msg = (
        f"the DAE's algebraic Jacobian (dg/dz, or [dF/dx' dF/dz]) became rank deficient at "
        f"t = {float(t.reshape(-1)[0]):.6g} for samples {idx[:10]}: the DAE is of index > 1 "
        "there (Theorem 9, Corollary 1) and implicit RK results would be meaningless; "
        "index-reduce the model (notes §5.4, §7.6.1)."
    )
    warnings.warn(msg, HighIndexWarning, stacklevel=4)
    messages.append(msg)
    status.masked_fill_(high, int(Status.NEWTON_FAILED))
    active.masked_fill_(high, False)
