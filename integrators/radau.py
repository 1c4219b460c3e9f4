"""Adaptive Radau IIA integration with per-sample step sizes (notes §7.4; Hairer-Wanner).

Every member of the batch has its own time, step size, Newton matrix, accept/reject decision
and status; a stiff member only makes the loop longer, never changes another member's steps.

Error estimate (derived for any odd ``s``). With ``gamma`` the real eigenvalue of ``A^{-1}``
and ``gamma_0 = 1 / gamma``, the embedded solution
``x_hat = x_k + h (gamma_0 x'_k + sum_i b_hat_i K_i)`` uses the nodes ``{0, c_1..c_s}`` and is
of order ``s`` when ``e = b_hat - b`` solves the quadrature conditions
``sum_i e_i c_i^(q-1) = -gamma_0 [q = 1]`` for ``q = 1..s`` (``b`` is exact to order 2s-1).
The raw difference ``delta = h (gamma_0 x'_k + sum_i e_i K_i)`` = O(h^(s+1)) is unbounded on
stiff components, so it is filtered with the real block of the already-factorised Newton
matrix, ``err = (gamma/h E + G)^{-1} (gamma/h) M delta`` (``M = dR/dK``), which for
``x' = f(x)`` is ``(I - h gamma_0 J)^{-1} delta`` (Hairer-Wanner IV.8). For ``s = 3`` this
reproduces scipy's / RADAU5's estimate (checked in tests). After a rejection the estimate
is refined once by re-evaluating ``f`` at ``x_k + err`` (explicit ODEs).

Step size: ``h_new = h * min(10, safety * min(1, pred) * err^(-1/(s+1)))`` with Gustafsson's
predictive factor ``pred`` and ``safety = 0.9 (2 k_max + 1) / (2 k_max + k)`` (``k`` Newton
iterations). The Jacobian is re-evaluated only when Newton contracted slowly
(``theta > 1e-3``) or failed; the factorisation is kept when the step would grow by < 20 %.
"""

from __future__ import annotations

import numpy as np
import torch

from ._irk_core import IRKCore, IterationMatrix
from ._irk_dense import StepRecords, extrapolate_stages
from ._irk_fixed import _flag_high_index
from .solution import Status

_REUSE_THETA = 1e-3
_MAX_FACTOR = 10.0
_MIN_FACTOR = 0.2


def embedded_weights(tab) -> tuple[float, np.ndarray]:
    """``(gamma, e)`` of the Radau IIA error estimate (see module docstring)."""
    s = tab.stages
    Ainv = np.linalg.inv(np.array(tab.A))
    lam = np.linalg.eigvals(Ainv)
    real = lam[np.abs(lam.imag) <= 1e-12 * np.abs(lam).max()].real
    gamma = float(real[0])
    c = np.array(tab.c)
    V = np.vander(c, s, increasing=True).T  # V[q, i] = c_i^q
    rhs = np.zeros(s)
    rhs[0] = -1.0 / gamma
    return gamma, np.linalg.solve(V, rhs)


def integrate_adaptive(
    core: IRKCore,
    x0,
    z0,
    xdot0,
    t,
    *,
    rtol,
    atol,
    max_steps,
    max_iter,
    newton_tol,
    index_tol,
    index_check_every=10,
    dt0=None,
):
    """Run adaptive Radau IIA; returns a dict of outputs, status, counters and messages."""
    batch = x0.shape[:-1]
    dev, dtype = x0.device, x0.dtype
    n, m, s = core.system.n, core.system.m, core.s
    gamma, e_np = embedded_weights(core.tab)
    e = torch.as_tensor(e_np, dtype=dtype, device=dev)
    c = torch.as_tensor(core.c, dtype=dtype, device=dev)
    expo = 1.0 / (s + 1)
    t_end = t[-1]
    span = float(t[-1] - t[0])
    min_step = 16 * core.eps

    def zeros(kind=torch.bool):
        return torch.zeros(batch, dtype=kind, device=dev)

    tcur = t[0].expand(batch).clone()
    x, z, xdot = x0, z0, xdot0
    status = zeros(torch.int8)
    active = torch.ones(batch, dtype=torch.bool, device=dev)
    need_jac = torch.ones(batch, dtype=torch.bool, device=dev)
    fresh = zeros()
    need_lu = torch.ones(batch, dtype=torch.bool, device=dev)
    h_fact = torch.zeros(batch, dtype=dtype, device=dev)
    first = torch.ones(batch, dtype=torch.bool, device=dev)
    rejected_last = zeros()
    nonfinite_last = zeros()
    have_prev = zeros()
    prev_W = torch.zeros(*batch, s, n + m, dtype=dtype, device=dev)
    prev_h = torch.ones(batch, dtype=dtype, device=dev)
    err_old = torch.ones(batch, dtype=dtype, device=dev)
    h_old = torch.zeros(batch, dtype=dtype, device=dev)
    n_steps, n_rej, n_newton, attempts = (zeros(torch.int64) for _ in range(4))
    messages: list[str] = []
    mat = IterationMatrix(core, index_tol)
    records = StepRecords(core.tab, n)
    dummy_W = torch.cat([torch.zeros_like(x0), z0], -1)[..., None, :].expand(*batch, s, n + m)
    records.append(tcur.clone(), torch.ones_like(tcur), x0, dummy_W, z0)

    h = _initial_step(core, x0, z0, xdot0, t[0], span, rtol, atol, expo, dt0)

    while bool(active.any()):
        remaining = t_end - tcur
        h = torch.where(active & (tcur + h >= t_end), remaining, h)
        tiny = active & (h <= min_step * torch.maximum(tcur.abs(), torch.ones_like(tcur)))
        _stop(
            tiny,
            torch.where(nonfinite_last, Status.NON_FINITE, Status.STEP_TOO_SMALL),
            status,
            active,
            messages,
            tcur,
            "the step size fell below the time resolution; the problem may be non-smooth, "
            "of index > 1, or blow up there — loosen the tolerances or check the model",
        )
        over = active & (attempts >= max_steps)
        _stop(
            over,
            Status.MAX_STEPS,
            status,
            active,
            messages,
            tcur,
            f"max_steps = {max_steps} step attempts were used; raise max_steps",
        )
        if not bool(active.any()):
            break
        tcol = tcur[..., None]
        jac_mask = active & need_jac
        if bool(jac_mask.any()):
            high = mat.update_jacobian(jac_mask, tcol, x.detach(), z.detach(), xdot.detach())
            _flag_high_index(high & active, status, active, messages, tcol)
            fresh = fresh | jac_mask
            need_lu = need_lu | jac_mask
            need_jac = need_jac & ~jac_mask
        lu_mask = active & (need_lu | (h != h_fact))
        singular = zeros()
        if bool(lu_mask.any()):
            singular = mat.update_factors(
                lu_mask, torch.where(lu_mask, h, h_fact.clamp_min(1e-300))
            )
            h_fact = torch.where(lu_mask, h, h_fact)
            need_lu = need_lu & ~lu_mask
        times = core.stage_times(tcol, h[..., None])
        inputs = core.stage_inputs(times, tcol, fixed=False)
        sc_x = atol + rtol * x.detach().abs()
        sc_z = atol + rtol * z.detach().abs()
        const = torch.cat([xdot.detach(), z.detach()], -1)[..., None, :].expand(*batch, s, n + m)
        W0 = torch.where(
            have_prev[..., None, None], extrapolate_stages(c, prev_W, h / prev_h), const
        )
        W, conv, iters, theta, nonfin = core.newton(
            times,
            inputs,
            h,
            x.detach(),
            W0,
            mat.factors,
            sc_x,
            sc_z,
            newton_tol,
            max_iter,
            active & ~singular,
        )
        n_newton += iters
        attempts += active.long()
        failed = active & (~conv | singular)
        # Newton failure: refresh a stale Jacobian at the same step, else halve the step.
        stale = failed & ~fresh
        need_jac = need_jac | stale
        halve = failed & fresh
        h = torch.where(halve, 0.5 * h, h)
        nonfinite_last = torch.where(failed, nonfin, nonfinite_last)
        rejected_last = rejected_last | failed
        n_rej += failed.long()

        ok = active & conv & ~singular
        Wg = core.ift(times, inputs, h, x, W, valid=ok)
        x_new = core.step_end(x, h, Wg)
        err = _error_norm(
            core,
            mat,
            x,
            x_new,
            xdot,
            W,
            h,
            gamma,
            e,
            tcol,
            inputs,
            sc_scale=(atol, rtol),
            z=z,
            retry=ok & (first | rejected_last),
        )
        finite = torch.isfinite(x_new.detach()).all(-1) & torch.isfinite(err)
        err = torch.where(finite, err, torch.full_like(err, float("inf")))
        accept = ok & (err < 1.0)
        reject = ok & ~accept
        n_rej += reject.long()

        safety = 0.9 * (2 * max_iter + 1) / (2 * max_iter + iters.to(dtype))
        err_c = err.clamp_min(1e-10)
        basic = err_c.pow(-expo)
        pred = torch.where(
            first | (h_old <= 0),
            torch.ones_like(h),
            h / h_old.clamp_min(1e-300) * (err_old / err_c).pow(expo),
        )
        factor = pred.clamp(max=1.0) * basic
        h_rej = h * torch.clamp(safety * factor, min=_MIN_FACTOR, max=1.0)
        h_rej = torch.where(finite, h_rej, 0.25 * h)
        grow = torch.clamp(safety * factor, max=_MAX_FACTOR)
        keep_lu = (theta <= _REUSE_THETA) & (grow < 1.2) & (grow >= 1.0)
        h_acc = torch.where(keep_lu, h, h * grow)

        # accepted samples advance
        z_new = W[..., -1, n:] if m else z
        zg = Wg[..., -1, n:] if m else z
        a1 = accept[..., None]
        if bool(accept.any()):
            records.append(
                torch.where(accept, tcur, records.t0[-1]),
                torch.where(accept, h, records.h[-1]),
                torch.where(a1, x, records.x[-1]),
                torch.where(accept[..., None, None], Wg, records.W[-1]),
                torch.where(a1, z, records.z[-1]),
            )
        xdot_new = _derivative(core, tcol + h[..., None], x_new.detach(), z_new, W, inputs)
        tcur = torch.where(accept, tcur + h, tcur)
        tcur = torch.where(accept & (tcur >= t_end - 1e-14 * abs(float(t_end))), t_end, tcur)
        x = torch.where(a1, x_new, x)
        z = torch.where(a1, zg, z)
        xdot = torch.where(a1, xdot_new, xdot)
        prev_W = torch.where(accept[..., None, None], W.detach(), prev_W)
        prev_h = torch.where(accept, h, prev_h)
        have_prev = have_prev | accept
        h_old = torch.where(accept, h, h_old)
        err_old = torch.where(accept, err_c.clamp_min(1e-2), err_old)
        need_jac = need_jac | (accept & (theta > _REUSE_THETA))
        fresh = fresh & ~accept
        first = first & ~accept
        rejected_last = torch.where(accept, zeros(), rejected_last | reject)
        n_steps += accept.long()
        if core.system.kind != "ode":  # periodic index check (Theorem 9) with a fresh Jacobian
            need_jac = need_jac | (accept & (n_steps % index_check_every == 0))
        h = torch.where(accept, h_acc, torch.where(reject, h_rej, h))
        done = accept & (tcur >= t_end)
        active = active & ~done

    x_out, z_out = records.evaluate(t)
    return dict(
        x=x_out,
        z=z_out,
        status=status,
        messages=messages,
        n_steps=n_steps,
        n_rejected=n_rej,
        n_newton=n_newton,
        n_jac=mat.n_jac,
        n_lu=mat.n_lu,
        n_f=core.n_f_evals,
        records=records,
    )


def _derivative(core, t, x, z, W, inputs):
    """``x'`` at the end of a step: ``f`` for the explicit kinds, ``K_s`` otherwise."""
    n = core.system.n
    if core.system.kind == "ode":
        core.n_f_evals += 1
        with torch.no_grad():
            return core.system.rhs_f(t, x, z, core.signal.at(t))
    return W[..., -1, :n].detach()


def _error_norm(core, mat, x, x_new, xdot, W, h, gamma, e, tcol, inputs, sc_scale, z, retry):
    """Scaled RMS norm (*batch,) of the filtered embedded error estimate."""
    atol, rtol = sc_scale
    n, m = core.system.n, core.system.m
    with torch.no_grad():
        K = W[..., :n]
        eK = gamma * (e @ K)
        M = mat.E[..., :, :n]
        sol = core.solver.solve_real_block(mat.factors, (M @ (xdot + eK)[..., None])[..., 0])
        sc = atol + rtol * torch.maximum(x.detach().abs(), x_new.detach().abs())
        err_x = sol[..., :n]
        if core.system.kind == "ode" and bool(retry.any()):
            core.n_f_evals += 1
            f_err = core.system.rhs_f(tcol, x.detach() + err_x, z, core.signal.at(tcol))
            sol2 = core.solver.solve_real_block(mat.factors, f_err + eK)
            err_x = torch.where(retry[..., None], sol2, err_x)
        parts = [(err_x / sc).square()]
        if m:
            z_new = W[..., -1, n:]
            sc_z = atol + rtol * torch.maximum(z.abs(), z_new.abs())
            err_z = (gamma / h)[..., None] * sol[..., n:]
            parts.append((err_z / sc_z).square())
        return torch.cat(parts, -1).mean(-1).sqrt()


def _initial_step(core, x0, z0, xdot0, t0, span, rtol, atol, expo, dt0):
    """First step: ``dt0`` or Hairer's estimate from ``x0``, ``x'(t0)`` (and ``f``'s change)."""
    batch = x0.shape[:-1]
    if dt0 is not None:
        return torch.full(batch, float(dt0), dtype=x0.dtype, device=x0.device)
    with torch.no_grad():
        sc = atol + rtol * x0.detach().abs()
        d0 = (x0.detach() / sc).square().mean(-1).sqrt()
        d1 = (xdot0 / sc).square().mean(-1).sqrt()
        h0 = torch.where(
            (d0 < 1e-5) | (d1 < 1e-5), torch.full_like(d0, 1e-6), 0.01 * d0 / d1.clamp_min(1e-300)
        )
        h0 = h0.clamp(max=span)
        if core.system.kind != "ode":
            return h0
        t1 = (t0 + h0)[..., None]
        x1 = x0.detach() + h0[..., None] * xdot0
        core.n_f_evals += 1
        f1 = core.system.rhs_f(t1, x1, z0, core.signal.at(t1))
        d2 = ((f1 - xdot0) / sc).square().mean(-1).sqrt() / h0
        dmax = torch.maximum(d1, d2)
        h1 = torch.where(
            dmax <= 1e-15,
            torch.clamp(h0 * 1e-3, min=1e-6),
            (0.01 / dmax.clamp_min(1e-300)).pow(expo),
        )
        return torch.minimum(100 * h0, h1).clamp(max=span)


def _stop(mask, code, status, active, messages, tcur, why):
    """Stop ``mask`` samples with status ``code`` (int or per-sample tensor) and a message."""
    if not bool(mask.any()):
        return
    codes = code if isinstance(code, torch.Tensor) else torch.full_like(status, int(code))
    status.copy_(torch.where(mask, codes.to(status.dtype), status))
    for idx in torch.nonzero(mask).tolist():
        idx = tuple(idx)
        name = Status(int(status[idx])).name
        messages.append(f"sample {idx}: {name} at t = {float(tcur[idx]):.6g}: {why}.")
    active.masked_fill_(mask, False)
