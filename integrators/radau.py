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

Step size: a controller of :mod:`integrators.controllers` maps the error norm to the next step;
the default :class:`~integrators.controllers.GustafssonController` is
``h_new = h * min(10, safety * min(1, pred) * err^(-1/(s+1)))`` with Gustafsson's predictive
factor ``pred`` and ``safety = 0.9 (2 k_max + 1) / (2 k_max + k)`` (``k`` Newton
iterations); an I or PI controller given by the user drives the steps instead. The Jacobian
is re-evaluated only when Newton failed or needed more than two iterations and contracted
slowly (``theta > 1e-3``; scipy's rule); the Gustafsson controller keeps the factorisation
when the step would grow by < 20 %.
"""

from __future__ import annotations

import numpy as np
import torch

from ._irk_core import IRKCore, IterationMatrix, host_shape, masked_update, to_device, to_host
from ._irk_dense import StepRecords, extrapolation_matrix, stop_times
from ._irk_fixed import _flag_high_index
from .controllers import GustafssonController
from .solution import Status


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
    controller=None,
):
    """Run adaptive Radau IIA; returns a dict of outputs, status, counters and messages.

    ``controller``: the step-size controller (default
    :class:`~integrators.controllers.GustafssonController`).

    The per-sample scalars (times, step sizes, flags, counters) live on the host as numpy
    arrays: the step-size control costs no device kernels, and each step needs one
    device-to-host transfer of the error norms (plus one per Newton iteration).
    """
    batch = x0.shape[:-1]
    dtype = x0.dtype
    hdt = np.float64 if dtype == torch.float64 else np.float32
    n, m, s = core.system.n, core.system.m, core.s
    controller = GustafssonController() if controller is None else controller
    gamma, e_np = embedded_weights(core.tab)
    gamma_e = torch.as_tensor(gamma * e_np, dtype=dtype, device=x0.device)
    rms = 1.0 / (n + m) ** 0.5
    c_np = np.array(core.c)
    c_col = c_np.reshape(s, *([1] * max(len(batch), 1)))
    expo = 1.0 / (s + 1)
    t_host = to_host(t).astype(hdt)
    t_end = t_host[-1]
    span = float(t_host[-1] - t_host[0])
    min_step = 16 * core.eps

    hshape = host_shape(batch)

    def flags(value=False):
        return np.full(hshape, value, dtype=bool)

    def counts():
        return np.zeros(hshape, dtype=np.int64)

    tcur = np.full(hshape, t_host[0], dtype=hdt)
    x, z, xdot = x0, z0, xdot0
    status = np.zeros(hshape, dtype=np.int8)
    active, need_jac, need_lu, first = flags(True), flags(True), flags(True), flags(True)
    fresh, rejected_last, nonfinite_last, have_prev = flags(), flags(), flags(), flags()
    h_fact = np.zeros(hshape, dtype=hdt)
    prev_W = None
    prev_h = np.ones(hshape, dtype=hdt)
    err_old = np.ones(hshape)
    h_old = np.zeros(hshape)
    n_steps, n_rej, n_newton, attempts = counts(), counts(), counts(), counts()
    messages: list[str] = []
    mat = IterationMatrix(core, index_tol)
    core.solver.want_real_block = True  # the error filter solves with the real block
    records = StepRecords(core.tab, n)
    dummy_W = torch.cat([torch.zeros_like(x0), z0], -1)[..., None, :].expand(*batch, s, n + m)
    records.append(tcur.reshape(batch), np.ones(batch, dtype=hdt), x0, dummy_W, z0)

    h = initial_step(core, x0, z0, xdot0, t[0], span, rtol, atol, expo, dt0)
    h = to_host(h, hshape).astype(hdt)

    while active.any():
        h = np.where(active & (tcur + h >= t_end), t_end - tcur, h)
        tiny = active & (h <= min_step * np.maximum(np.abs(tcur), 1.0))
        if tiny.any():
            escape = tiny & ~nonfinite_last & (core.system.kind != "ode")
            escape &= escaping(x, z, x0, z0, hshape) if escape.any() else escape
            stop_samples(
                escape,
                Status.NON_FINITE,
                status,
                active,
                messages,
                tcur,
                "the step size fell below the time resolution while the states grew beyond "
                f"{ESCAPE_GROWTH:.1e} times their initial size: the solution escapes to "
                "infinity there (finite escape time, like x' = x^2, x(0) = 1 at t = 1, notes "
                "eq. 1.44); its outputs from there on are not defined",
            )
            tiny &= ~escape
            stop_samples(
                tiny,
                np.where(nonfinite_last, Status.NON_FINITE, Status.STEP_TOO_SMALL),
                status,
                active,
                messages,
                tcur,
                "the step size fell below the time resolution; the problem may be non-smooth, "
                "of index > 1, or blow up there — loosen the tolerances or check the model",
            )
        over = active & (attempts >= max_steps)
        stop_samples(
            over,
            Status.MAX_STEPS,
            status,
            active,
            messages,
            tcur,
            f"max_steps = {max_steps} step attempts were used; raise max_steps",
        )
        if not active.any():
            break
        h_step = h
        # one transfer: t_k, h, t_k + h and the stage times t_k + c_i h, each (*batch,)
        host = np.empty((3 + s, *hshape), dtype=hdt)
        host[0], host[1], host[2], host[3:] = tcur, h, tcur + h, tcur + c_col * h
        on_dev = to_device(host, x0, dtype, shape=(3 + s, *batch))[..., None]
        tcol, h_t, t_next = on_dev[0], on_dev[1, ..., 0], on_dev[2]
        xd, zd = x.detach(), z.detach()
        jac_mask = active & need_jac
        if jac_mask.any():
            high = mat.update_jacobian(jac_mask, tcol, xd, zd, xdot.detach())
            _flag_high_index(high & active, status, active, messages, tcur)
            fresh |= jac_mask
            need_lu |= jac_mask
            need_jac &= ~jac_mask
        lu_mask = active & (need_lu | (h != h_fact))
        singular = flags()
        if lu_mask.any():
            h_lu = (
                h_t
                if lu_mask.all()
                else to_device(
                    np.where(lu_mask, h, np.where(h_fact > 0, h_fact, h)), x0, dtype, batch
                )
            )
            singular = mat.update_factors(lu_mask, h_lu)
            h_fact = np.where(lu_mask, h, h_fact)
            need_lu &= ~lu_mask
        times = core.stage_times(tcol, h_t[..., None], len(batch), stacked=on_dev[3:])
        inputs = core.stage_inputs(times, tcol, fixed=False)
        sc_x = atol + rtol * xd.abs()
        sc_z = atol + rtol * zd.abs() if m else zd
        W0 = _stage_guess(c_np, prev_W, have_prev, h / prev_h, xdot.detach(), zd, s)
        W, conv, iters, theta, nonfin = core.newton(
            times,
            inputs,
            h_t,
            xd,
            W0,
            mat.factors,
            sc_x,
            sc_z,
            newton_tol,
            max_iter,
            active & ~singular,
        )
        n_newton += iters
        attempts += active
        failed = active & (~conv | singular)
        # Newton failure: refresh a stale Jacobian at the same step, else halve the step.
        need_jac |= failed & ~fresh
        h = np.where(failed & fresh, 0.5 * h, h)
        nonfinite_last = np.where(failed, nonfin, nonfinite_last)
        rejected_last |= failed
        n_rej += failed

        ok = active & conv & ~singular
        Wg = core.ift(times, inputs, h_t, x, W, valid=ok)
        x_new = core.step_end(x, h_t, Wg)
        err = _error_norm(
            core,
            mat,
            x_new,
            xdot,
            W,
            h_t,
            gamma_e,
            gamma,
            tcol,
            xd,
            sc_x,
            (atol, rtol),
            z=zd,
            retry=ok & (first | rejected_last),
        )
        finite_x = torch.isfinite(x_new.detach()).all(-1).to(err.dtype)
        err, finite_x = to_host(torch.stack([err, finite_x]), (2, *hshape)).astype(np.float64)
        err *= rms
        finite = (finite_x > 0) & np.isfinite(err)
        err = np.where(finite, err, np.inf)
        accept = ok & (err < 1.0)
        reject = ok & ~accept
        n_rej += reject

        hh = h_step.astype(np.float64)
        err_c, h_acc, h_rej, slow = controller.radau_step_sizes(
            hh, err, finite, err_old, h_old, first, iters, theta, max_iter, expo
        )

        if accept.any():  # accepted samples advance
            t0 = np.where(accept, tcur, np.inf).astype(hdt)
            records.append(t0.reshape(batch), h_step.reshape(batch), x, Wg, z)
            z_new = W[..., -1, n:] if m else z
            xdot_new = _derivative(core, t_next, x_new.detach(), z_new, W)
            x = masked_update(accept, x_new, x)
            z = masked_update(accept, Wg[..., -1, n:], z) if m else z
            xdot = masked_update(accept, xdot_new, xdot)
            prev_W = W if prev_W is None else masked_update(accept, W, prev_W)
        tcur = np.where(accept, tcur + h_step, tcur)
        tcur = np.where(accept & (tcur >= t_end - 1e-14 * abs(float(t_end))), t_end, tcur)
        prev_h = np.where(accept, h_step, prev_h)
        have_prev |= accept
        h_old = np.where(accept, hh, h_old)
        err_old = np.where(accept, np.maximum(err_c, 1e-2), err_old)
        need_jac |= accept & slow
        fresh &= ~accept
        first &= ~accept
        rejected_last = ~accept & (rejected_last | reject)
        n_steps += accept
        if core.system.kind != "ode":  # periodic index check (Theorem 9) with a fresh Jacobian
            need_jac |= accept & (n_steps % index_check_every == 0)
        h = np.where(accept, h_acc, np.where(reject, h_rej, h)).astype(hdt)
        active &= ~(accept & (tcur >= t_end))

    records.stop = stop_times(status, tcur)
    x_out, z_out = records.evaluate(t)

    def dev(a):
        return torch.from_numpy(a).to(x0.device).reshape(batch)

    return dict(
        x=x_out,
        z=z_out,
        status=dev(status),
        messages=messages,
        n_steps=dev(n_steps),
        n_rejected=dev(n_rej),
        n_newton=dev(n_newton),
        n_jac=mat.n_jac,
        n_lu=mat.n_lu,
        n_f=core.n_f_evals,
        records=records,
    )


def _stage_guess(c, prev_W, have_prev, ratio, xdot, z, s):
    """Newton start: the previous step's extrapolated stage polynomial, else ``(x', z)``."""
    if have_prev.any():
        L = extrapolation_matrix(c, ratio)
        L = to_device(L, prev_W, prev_W.dtype, shape=(*prev_W.shape[:-2], *L.shape[-2:]))
        ext = L @ prev_W
        if have_prev.all():
            return ext
    const = torch.cat([xdot, z], -1)[..., None, :]
    const = const.expand(*xdot.shape[:-1], s, const.shape[-1])
    if not have_prev.any():
        return const
    return masked_update(have_prev, ext, const)


def _derivative(core, t, x, z, W):
    """``x'`` at the end of a step: ``f`` for the explicit kinds, ``K_s`` otherwise."""
    n = core.system.n
    if core.system.kind == "ode":
        core.n_f_evals += 1
        with torch.no_grad():
            return core.system.rhs_f(t, x, z, core.signal.at(t))
    return W[..., -1, :n].detach()


def _error_norm(core, mat, x_new, xdot, W, h, gamma_e, gamma, tcol, x, sc_x, tol, z, retry):
    """Scaled norm (*batch,) of the filtered embedded error estimate, times ``sqrt(n + m)``
    (the RMS factor is applied on the host); ``retry`` (host bool) marks the samples whose
    estimate is refined by one more ``f`` evaluation. ``gamma_e = gamma e``, ``x`` the
    detached step start, ``sc_x = atol + rtol |x|``, ``tol = (atol, rtol)``."""
    atol, rtol = tol
    n, m = core.system.n, core.system.m
    ode = core.system.kind == "ode"
    with torch.no_grad():
        eK = gamma_e @ (W[..., :n] if m else W)
        rhs = xdot + eK
        if not ode:  # M = dR/dK (the identity for explicit ODEs)
            rhs = (mat.E[..., :, :n] @ rhs[..., None])[..., 0]
        sol = core.solver.solve_real_block(mat.factors, rhs)
        sc = torch.maximum(sc_x, atol + rtol * x_new.detach().abs())
        err_x = sol[..., :n] if m else sol
        if ode and retry.any():
            core.n_f_evals += 1
            f_err = core.system.rhs_f(tcol, x + err_x, z, core.signal.at(tcol))
            sol2 = core.solver.solve_real_block(mat.factors, f_err + eK)
            err_x = masked_update(retry, sol2, err_x)
        q = torch.linalg.vector_norm(err_x / sc, dim=-1)
        if m:
            z_new = W[..., -1, n:]
            sc_z = atol + rtol * torch.maximum(z.abs(), z_new.abs())
            err_z = (gamma / h)[..., None] * sol[..., n:]
            q = torch.hypot(q, torch.linalg.vector_norm(err_z / sc_z, dim=-1))
        return q


def initial_step(core, x0, z0, xdot0, t0, span, rtol, atol, expo, dt0):
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


ESCAPE_GROWTH = 1e8  # growth of max |(x, z)| taken, at a collapsed step, as a finite escape


def escaping(x, z, x0, z0, hshape) -> np.ndarray:
    """(*batch,) host bool: samples whose largest state magnitude ``max |(x, z)|`` exceeds
    ``ESCAPE_GROWTH`` times that at the start (at least 1). Evaluated where the step size has
    collapsed: an implicit method approaching a finite escape time keeps finite states (its
    stage equations lose their solution first), so the growth, not an inf, tells the escape
    apart from a non-smooth or high-index point, where the states stay moderate."""

    def size(a, b):
        v = torch.cat([a.detach(), b.detach()], -1).abs()
        return v.amax(-1) if v.shape[-1] else v.new_zeros(v.shape[:-1])

    grown = size(x, z) > ESCAPE_GROWTH * size(x0, z0).clamp_min(1.0)
    return to_host(grown, hshape)


def stop_samples(mask, code, status, active, messages, tcur, why):
    """Stop ``mask`` samples with status ``code`` (int or per-sample array) and a message; the
    other arguments but the strings are host (numpy) arrays, updated in place."""
    if not mask.any():
        return
    codes = np.broadcast_to(np.asarray(code, dtype=np.int8), status.shape)
    status[mask] = codes[mask]
    for idx in np.argwhere(mask).tolist():
        idx = tuple(idx)
        name = Status(int(status[idx])).name
        when = float(tcur[idx])
        messages.append(
            f"sample {idx}: {name} at t = {when:.6g}: {why}; its outputs after t = {when:.6g} "
            "are NaN."
        )
    active[mask] = False
