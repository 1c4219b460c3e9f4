"""Adaptive Radau IIA for one trajectory: the host loop with the step control in Python floats.

The algorithm is the one of :func:`integrators.radau.adaptive_loop` with the numpy kernel
:class:`integrators._radau_host.NumpyKernel` (notes §7.4, simplified Newton eq. 7.14-7.16,
step eq. 7.18): the same initial step, stage guess, theta-controlled simplified Newton,
Jacobian and factorisation reuse, filtered embedded error estimate with its retry, step-size
rule, statuses and messages, so it takes the same steps. With one trajectory
every per-sample quantity (time, step size, flags, error norm, contraction rate) is a Python
float or bool, whose operations cost far less than those on a one-element numpy array: on the
stiff Van der Pol oscillator of ``bench_implicit`` this loop takes about 0.6 times the time of
the shared loop with the numpy kernel at batch 1. The stage vectors and the small Newton
algebra stay numpy arrays shaped (1, ...) and go through the numpy kernel's helpers
(factorisation, error filter, model wrapper, dense-output records and the gradient replay).

Only float64 states take this path (:func:`single_loop_supported`): Python floats are float64,
so its step control rounds as the batched loop's does (up to a bit of ``**``, and the summation
order of the Newton and error norms; the tests check that the steps are the same).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ._irk_core import IRKCore, host_shape
from ._irk_dense import stop_times
from ._radau_host import _factorize, _HostModel, _method_constants, _records, _run_constants
from .controllers import GustafssonController
from .radau import initial_step, stop_samples
from .solution import Status

#: The step-size rule of the host drivers (they run only with the default controller).
_RULE = GustafssonController()


def single_loop_supported(x0: torch.Tensor) -> bool:
    """Whether a problem that the host loop runs can take the one-trajectory loop: a single
    trajectory (``x0.numel() == n``) in float64."""
    return x0.dtype == torch.float64 and x0.numel() == x0.shape[-1]


def integrate_single_host(
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
    dt0=None,
):
    """Run adaptive Radau IIA on one float64 trajectory; same arguments and returned dict as
    :func:`integrators._radau_host.integrate_adaptive_host`.

    Args:
        core: :class:`IRKCore` of an explicit ODE with ``core.solver.dense(n)``.
        x0: (*batch, n) initial state with one member (CPU, float64); z0: (*batch, 0);
            xdot0: (*batch, n) ``f(t0, x0)``.
        t: (T,) output times.
        rtol, atol, max_steps, max_iter, newton_tol, dt0: as in ``integrate_adaptive``.
    """
    batch = x0.shape[:-1]
    hshape = host_shape(batch)
    n, s = core.system.n, core.s
    model = _HostModel(core, batch, np.float64)
    (gamma_e, filt, A, b, c, lagrange, powers, rms, rms_newton, expo) = _method_constants(
        core, np.float64
    )
    A_kron = np.kron(A, np.eye(n))
    t_host, t_end, t_snap, span, min_step, tiny, atol_, rtol_ = _run_constants(
        core, t, atol, rtol, np.float64
    )
    t_end, t_snap = float(t_end), float(t_snap)

    tcur = float(t_host[0])
    x = x0.detach().numpy().astype(np.float64).reshape(1, n)
    xdot = xdot0.detach().numpy().astype(np.float64).reshape(1, n)
    z = z0.detach()
    status = Status.SUCCESS
    active, need_jac, need_lu, first = True, True, True, True
    fresh = rejected_last = nonfinite_last = False
    h_fact = 0.0
    G = J_inv = real_inv = prev_W = None
    prev_h, err_old, h_old = 1.0, 1.0, 0.0
    n_steps = n_rej = n_newton = attempts = 0
    n_jac = n_lu = 0
    messages: list[str] = []
    accepted: list[tuple] = []
    accept_mask = np.ones(1, dtype=bool)

    def stop(code, why):
        """Status ``code`` and the batched loops' message for the one sample."""
        status_arr, active_arr = np.zeros(hshape, dtype=np.int8), np.ones(hshape, dtype=bool)
        stop_samples(active_arr.copy(), code, status_arr, active_arr, messages,
                     np.full(hshape, tcur), why)  # fmt: skip
        return Status(int(status_arr.reshape(-1)[0]))

    h = initial_step(core, x0, z0, xdot0, t[0], span, rtol, atol, expo, dt0)
    h = float(h.detach().reshape(()))

    # no gradient recording, and not inference mode: models that call autograd inside ``f``
    # need ``enable_grad`` to work there
    with np.errstate(all="ignore"), torch.no_grad():
        while active:
            if tcur + h >= t_end:
                h = t_end - tcur
            if h <= min_step * max(abs(tcur), 1.0):
                status = stop(
                    Status.NON_FINITE if nonfinite_last else Status.STEP_TOO_SMALL,
                    "the step size fell below the time resolution; the problem may be "
                    "non-smooth, of index > 1, or blow up there — loosen the tolerances or "
                    "check the model",
                )
                break
            if attempts >= max_steps:
                status = stop(
                    Status.MAX_STEPS,
                    f"max_steps = {max_steps} step attempts were used; raise max_steps",
                )
                break
            h_step = h
            # t_k, t_k + h and the stage times t_k + c_i h, as (2 + s, 1) host times
            host = np.empty((2 + s, 1))
            host[0], host[1], host[2:, 0] = tcur, tcur + h, tcur + c * h
            if need_jac:
                with torch.no_grad():
                    G_t = core.frozen_blocks(
                        model.times(host[0]), model.state(x), z, model.state(xdot)
                    )[1]
                G = model.back(G_t, np.empty((1, n, n)))
                n_jac += 1
                fresh = need_lu = True
                need_jac = False
            singular = False
            if need_lu or h != h_fact:
                J_inv, real_inv, sing = _factorize(A, filt, G, np.array([h]))
                singular = bool(sing[0])
                n_lu += 1
                h_fact = h
                need_lu = False
            sc_x = atol_ + rtol_ * np.abs(x)
            if prev_W is None:
                W = np.repeat(xdot[:, None, :], s, axis=1)
            else:  # previous stage polynomial at the new nodes 1 + c_i h / h_prev
                tau = 1.0 + c * (h / prev_h)
                W = ((tau[:, None] ** powers) @ lagrange) @ prev_W
            conv = nonfin = False
            iters, theta = 0, 0.0
            if not singular:
                W, conv, iters, theta, nonfin = _newton(
                    model, A_kron, model.times(host[2:]), host[0], h, x, z, W, J_inv, sc_x,
                    newton_tol, max_iter, rms_newton, tiny,
                )  # fmt: skip
            n_newton += iters
            attempts += 1
            if not conv or singular:  # refresh a stale Jacobian at the same step, else halve
                if fresh:
                    h = 0.5 * h
                else:
                    need_jac = True
                nonfinite_last = nonfin
                rejected_last = True
                n_rej += 1
                continue

            Wg = W if math.isfinite(W.sum()) else np.nan_to_num(W)
            x_new = x + h_step * (b @ Wg)  # eq. 7.18
            # filtered embedded error estimate (see integrators.radau), refined after rejections
            eK = gamma_e @ W[0]
            err_x = real_inv[0] @ (xdot[0] + eK)
            if first or rejected_last:
                f_err = model.f(host[0], x + err_x, z)
                err_x = real_inv[0] @ (f_err[0] + eK)
            sc = np.maximum(sc_x[0], atol_ + rtol_ * np.abs(x_new[0]))
            q = err_x / sc
            err = math.sqrt(q @ q) * rms
            finite = math.isfinite(err) and (
                math.isfinite(x_new.sum()) or bool(np.isfinite(x_new).all())
            )
            if not finite:
                err = math.inf
            err_c, h_acc, h_rej, slow = _RULE.radau_step_size(
                h_step, err, finite, err_old, h_old, first, iters, theta, max_iter, expo
            )
            if err >= 1.0:
                n_rej += 1
                rejected_last = True
                h = h_rej
                continue

            accepted.append((np.array([tcur]), np.array([h_step]), accept_mask, W, host, Wg, x))
            xdot = model.f(host[1], x_new, z)
            x = x_new
            prev_W = W
            tcur = tcur + h_step
            if tcur >= t_snap:
                tcur = t_end
            prev_h = h_old = h_step
            err_old = max(err_c, 1e-2)
            need_jac = need_jac or slow
            fresh = first = rejected_last = False
            n_steps += 1
            h = h_acc
            active = tcur < t_end

    records = _records(core, model, x0, z0, t_host[0], accepted)
    records.stop = stop_times(np.full(hshape, int(status)), tcur)
    x_out, z_out = records.evaluate(t)

    def dev(value, dtype):
        return torch.full(batch, value, dtype=dtype)

    return dict(
        x=x_out,
        z=z_out,
        status=dev(int(status), torch.int8),
        messages=messages,
        n_steps=dev(n_steps, torch.int64),
        n_rejected=dev(n_rej, torch.int64),
        n_newton=dev(n_newton, torch.int64),
        n_jac=n_jac,
        n_lu=n_lu,
        n_f=core.n_f_evals,
        records=records,
    )


def _newton(model, A_kron, t_stage, tk, h, xk, z, W, J_inv, sc_x, tol, max_iter, rms, tiny):
    """Simplified Newton on ``R(W) = K - f(t_k + c h, x_k + h A K)`` (eq. 7.14-7.16) for one
    trajectory, with the stopping and divergence rules of the batched host loop.

    Args:
        A_kron: (s n, s n) ``A (x) I``; t_stage: (s, *batch, 1) stage-time tensor; tk: (1,)
            host step start; h: step size; xk, sc_x: (1, n); W: (1, s, n) initial guess;
            z: the (empty) algebraic state tensor; J_inv: (1, 2 s n, s n) ``-J^{-1}`` stacked
            over ``(A (x) I) (-J^{-1})``; rms: ``1 / sqrt(s n)``; tiny: smallest normal float64.

    Returns:
        ``(W, converged, iterations, theta, non_finite)``.
    """
    _, s, n = W.shape
    sn = s * n
    J = J_inv[0]
    hA = h * A_kron
    x_rep = np.tile(xk[0], s)  # x_k at every stage, (s n,)
    w = np.tile(h / sc_x[0] * rms, s)  # weights of the stage increments h (A dK)_i / sc_x
    Wv = W.reshape(sn)
    theta, norm_old = 0.0, None
    for it in range(max_iter):
        X = hA @ Wv
        X += x_rep  # stage states, stage-major (s n,)
        if model.core.stack_stages is None:
            K1, X1 = Wv.reshape(1, s, n), X.reshape(1, s, n)
            model.decide_stacking(tk, np.array([h]), t_stage, K1, X1)
        F = model.stages(t_stage, X.reshape(s, 1, n), z)
        both = J @ (Wv - F.reshape(sn))  # (dW, A dK) in one product
        v = both[sn:] * w
        norm = math.sqrt(v @ v)
        if not math.isfinite(norm):
            return Wv.reshape(1, s, n), False, it, theta, True
        if norm_old is None:
            done = norm == 0.0
        else:  # contraction theta; theta / (1 - theta) ||dW|| <= tol converges
            th = norm / max(norm_old, tiny)
            theta = th
            rate = norm / max(1.0 - th, 1e-12)
            # diverging, or predicted to miss tol within max_iter iterations: give up
            if not (th < 1.0 and th ** (max_iter - it) * rate <= tol):
                return Wv.reshape(1, s, n), False, it, theta, False
            done = th * rate <= tol
        Wv = Wv + both[:sn]
        if done:
            return Wv.reshape(1, s, n), True, it + 1, theta, False
        norm_old = norm
    return Wv.reshape(1, s, n), False, max_iter, theta, False
