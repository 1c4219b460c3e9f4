"""Adaptive Radau IIA integration with per-sample step sizes (notes §7.4; Hairer-Wanner).

Every member of the batch has its own time, step size, Newton matrix, accept/reject decision
and status; a stiff member only makes the loop longer, never changes another member's steps.

Structure: :func:`adaptive_loop` is the algorithm (initial step, step-size control,
accept / reject, Jacobian and factorisation reuse, statuses, dense-output bookkeeping) on
per-sample host quantities (:mod:`integrators._per_sample`); the per-step work (Jacobian,
factorisation of the Newton matrix, simplified Newton on the stages, error estimate, moving
the states) sits behind the small :class:`RadauKernel` interface. Three kernels implement it:
:class:`TorchKernel` on torch tensors (every system kind, any device),
:class:`integrators._radau_host.NumpyKernel` on numpy arrays (small explicit ODEs on the CPU)
and :class:`integrators._radau_host.OneTrajectoryKernel`, the numpy kernel for a single
float64 trajectory, with which the loop keeps its per-sample quantities as Python floats.
``integrators.implicit`` chooses the kernel (:func:`integrators._radau_host.use_host_loop`,
:func:`integrators._radau_host.one_trajectory`) and reports it in ``stats.extra["driver"]``.

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

import contextlib
from typing import Protocol

import numpy as np
import torch

from ._irk_core import IRKCore, IterationMatrix, host_shape, masked_update, to_device, to_host
from ._irk_dense import StepRecords, extrapolation_matrix, nan_beyond, stop_times
from ._irk_fixed import _flag_high_index
from ._irk_linalg import real_eigenvalue_of_inverse
from ._per_sample import ArrayOps, ScalarOps
from .controllers import GustafssonController, initial_step
from .solution import Status


def embedded_weights(tab) -> tuple[float, np.ndarray]:
    """``(gamma, e)`` of the Radau IIA error estimate (see module docstring)."""
    s = tab.stages
    gamma = real_eigenvalue_of_inverse(tab.A)
    c = np.array(tab.c)
    V = np.vander(c, s, increasing=True).T  # V[q, i] = c_i^q
    rhs = np.zeros(s)
    rhs[0] = -1.0 / gamma
    return gamma, np.linalg.solve(V, rhs)


class RadauKernel(Protocol):
    """The per-step work of :func:`adaptive_loop` on one representation of the states.

    The loop owns every per-sample quantity: times, step sizes, flags, counters, statuses,
    the controller's history, as host arrays shaped :func:`host_shape` ``(*batch,)`` (or
    Python scalars, see ``scalar``). A kernel owns the states ``x, z, x'`` and the stages, the
    frozen Jacobian and the Newton matrices, and the dense-output records; it receives masks
    and step sizes and returns masks and numbers in the loop's representation. Attributes
    ``n_jac`` and ``n_lu`` count Jacobian evaluations and factorisations.
    """

    n_jac: int
    n_lu: int
    #: True for a one-trajectory kernel: the loop passes masks, times and step sizes as
    #: Python bools and floats (:class:`integrators._per_sample.ScalarOps`) instead of host
    #: arrays (*batch,), and the kernel returns its per-sample results the same way.
    scalar: bool

    def begin_step(self, tcur: np.ndarray, h: np.ndarray) -> None:
        """Prepare a step attempt from the step starts ``tcur`` and sizes ``h``."""

    def jacobian(self, mask: np.ndarray) -> np.ndarray | None:
        """Re-evaluate the frozen Jacobian at the step start for the ``mask`` samples; return
        the samples whose DAE index check failed (None: no check)."""

    def factorize(self, mask: np.ndarray, h: np.ndarray, h_fact: np.ndarray) -> np.ndarray:
        """Factorise the Newton matrix (eq. 7.16) at step ``h`` for the ``mask`` samples (the
        others keep theirs, made at ``h_fact``); return the singular samples."""

    def newton(self, live, have_prev, ratio) -> tuple:
        """Simplified Newton (eq. 7.14-7.16) on the ``live`` samples, started at the previous
        stage polynomial extrapolated by the step ratio ``ratio`` where ``have_prev``; return
        ``(converged, iterations, theta, non_finite)``."""

    def error(self, ok: np.ndarray, retry: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Step ends of the ``ok`` samples and their scaled error norms (float64, inf where not
        finite; ``retry`` samples refine the estimate once); return ``(err, finite)``."""

    def advance(self, accept: np.ndarray, tcur: np.ndarray, h: np.ndarray) -> None:
        """Move the ``accept`` samples to their step ends and record the steps ``[tcur, tcur
        + h]`` for dense output."""

    def restart(self, mask: np.ndarray, tcur: np.ndarray) -> None:
        """At an input breakpoint ``tcur`` reached by the ``mask`` samples: ``x'`` consistent
        with the input from there on, for the next step's error estimate (called for DAEs and
        implicit ODEs only, whose ``x'`` at a step end is the step's last stage, solved with
        the input before the breakpoint). The recorded ``z`` stays the step end's: outputs at a
        sample time hold the input of the interval that ends there, as at fixed steps."""

    def escaping(self) -> np.ndarray:
        """:func:`escaping` at the current states (called for DAEs and implicit ODEs only)."""

    def records(self) -> StepRecords:
        """The dense-output records of the accepted steps."""

    def step_mode(self) -> contextlib.AbstractContextManager:
        """The context the step loop runs in (the records and outputs are made outside it)."""


def adaptive_loop(
    kernel: RadauKernel,
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
    index_check_every=10,
    dt0=None,
    controller=None,
):
    """Run adaptive Radau IIA with ``kernel``'s per-step work; returns a dict of outputs,
    status, counters and messages.

    The loop is the algorithm of the module docstring: step-size control by ``controller``
    (default :class:`~integrators.controllers.GustafssonController`), Jacobian and
    factorisation reuse, accept / reject, statuses (``STEP_TOO_SMALL``, ``NON_FINITE``,
    ``MAX_STEPS``, ``HIGH_INDEX``) and their messages, all on per-sample host quantities in the
    kernel's representation (:mod:`integrators._per_sample`: arrays (*batch,), or Python
    scalars for a one-trajectory kernel); the kernel carries out each step.

    Args:
        kernel: a :class:`RadauKernel` made for this problem.
        core: the :class:`IRKCore` of the problem; x0, z0, xdot0: (*batch, n), (*batch, m),
            (*batch, n) initial states and ``x'(t0)``; t: (T,) output times.
        rtol, atol: error tolerances; max_steps: step attempts per sample; max_iter: Newton
            iterations per step; index_check_every: accepted steps between DAE index checks;
            dt0: first trial step (None: Hairer's estimate); controller: step-size controller.
    """
    batch = x0.shape[:-1]
    hdt = np.float64 if x0.dtype == torch.float64 else np.float32
    hshape = host_shape(batch)
    ops = (ScalarOps if kernel.scalar else ArrayOps)(hshape, hdt)
    where, pick, any_, not_ = ops.where, ops.pick, ops.any, ops.not_
    s = core.s
    ode = core.system.kind == "ode"
    controller = GustafssonController() if controller is None else controller
    expo = 1.0 / (s + 1)
    t_host = to_host(t).astype(hdt)
    t_end = t_host[-1].item() if ops.scalar else t_host[-1]
    span = float(t_host[-1] - t_host[0])
    # steps end at the stops: the input's breakpoints inside (t0, t_end), and t_end
    stops = t_host[[0, -1]]
    breaks = getattr(core.signal.source, "breakpoints", None)
    if breaks is not None:
        grid = to_host(breaks).astype(hdt)
        stops = np.concatenate([stops[:1], grid[(grid > stops[0]) & (grid < stops[1])], stops[1:]])
    if ops.scalar:
        stops = stops.tolist()
    next_stop = ops.counts() + 1  # index of each sample's next stop
    min_step = 16 * core.eps

    tcur = ops.full(t_host[0])
    status = ops.back(np.zeros(hshape, dtype=np.int8))
    active, need_jac, need_lu, first = (ops.flags(True) for _ in range(4))
    fresh, rejected_last, nonfinite_last, have_prev = (ops.flags() for _ in range(4))
    h_fact = ops.full(0.0)
    prev_h = ops.full(1.0)
    err_old = ops.float64(ops.full(1.0))
    h_old = ops.float64(ops.full(0.0))
    n_steps, n_rej, n_newton, attempts = (ops.counts() for _ in range(4))
    messages: list[str] = []

    def on_host(update, mask):
        """Apply ``update(mask, status, active, messages, tcur)``, which stops samples in
        place on host arrays (:func:`stop_samples`, :func:`_flag_high_index`), to the
        loop's status and active flags in their representation."""
        nonlocal status, active
        st, ac = ops.host(status, np.int8), ops.host(active)
        update(ops.host(mask) & ac, st, ac, messages, ops.host(tcur))
        status, active = ops.back(st), ops.back(ac)

    def stop(mask, code, why):
        """Stop the ``mask`` samples with status ``code`` and the message ``why``."""
        on_host(lambda m, st, ac, msgs, tc: stop_samples(m, code, st, ac, msgs, tc, why), mask)

    h = ops.from_tensor(_first_step(core, x0, z0, xdot0, t[0], span, rtol, atol, s, dt0))

    with kernel.step_mode():
        while any_(active):
            t_stop = stops[next_stop]
            h_planned = h
            # a step that would reach the stop, or leave less than the smallest step before
            # it, ends on it (its time is set to the stop: no sliver left by rounding)
            to_stop = active & (tcur + h + min_step * ops.maximum(ops.abs(tcur), 1.0) >= t_stop)
            h = where(to_stop, t_stop - tcur, h)
            tiny = active & (h <= min_step * ops.maximum(ops.abs(tcur), 1.0))
            if any_(tiny):
                escape = tiny & not_(nonfinite_last)
                if not ode and any_(escape):
                    escape &= ops.back(kernel.escaping())
                    stop(
                        escape,
                        Status.NON_FINITE,
                        "the step size fell below the time resolution while the states grew "
                        f"beyond {ESCAPE_GROWTH:.1e} times their initial size: the solution "
                        "escapes to infinity there (finite escape time, like x' = x^2, x(0) = 1 "
                        "at t = 1, notes eq. 1.44); its outputs from there on are not defined",
                    )
                    tiny &= not_(escape)
                stop(
                    tiny & nonfinite_last,
                    Status.NON_FINITE,
                    "the model's functions or the stage values became inf/nan in every trial "
                    "step until the step size fell below the time resolution; check the "
                    "model there for a division by zero, a log or sqrt of a negative "
                    "argument or a finite escape time",
                )
                stop(
                    tiny & not_(nonfinite_last),
                    Status.STEP_TOO_SMALL,
                    "the step size fell below the time resolution; the problem may be non-smooth, "
                    "of index > 1, or blow up there — loosen the tolerances or check the model",
                )
            over = active & (attempts >= max_steps)
            if any_(over):
                why = f"max_steps = {max_steps} step attempts were used; raise max_steps"
                stop(over, Status.MAX_STEPS, why)
            if not any_(active):
                break
            # the step ends at a float time and moves the state by exactly its length; the
            # planned h_try decides the reuse of the factorisation and the next step size
            h_try, h_step = h, (tcur + h) - tcur
            kernel.begin_step(tcur, h_step)
            jac_mask = active & need_jac
            if any_(jac_mask):
                high = kernel.jacobian(jac_mask)
                if high is not None:
                    on_host(_flag_high_index, ops.back(high))
                fresh |= jac_mask
                need_lu |= jac_mask
                need_jac &= not_(jac_mask)
            lu_mask = active & (need_lu | (h != h_fact))
            singular = ops.flags()
            if any_(lu_mask):
                singular = kernel.factorize(lu_mask, h, h_fact)
                h_fact = where(lu_mask, h, h_fact)
                need_lu &= not_(lu_mask)
            conv, iters, theta, nonfin = kernel.newton(
                active & not_(singular), have_prev, h / prev_h
            )
            n_newton += iters
            attempts += active
            failed = active & (not_(conv) | singular)
            if any_(failed):  # refresh a stale Jacobian at the same step, else halve the step
                need_jac |= failed & not_(fresh)
                h = where(failed & fresh, 0.5 * h, h)
                nonfinite_last = where(failed, nonfin, nonfinite_last)
                rejected_last |= failed
                n_rej += failed

            ok = active & conv & not_(singular)
            if not any_(ok):
                continue
            err, finite = kernel.error(ok, ok & (first | rejected_last))
            accept = ok & (err < 1.0)
            reject = ok & not_(accept)
            n_rej += reject

            hh = ops.float64(h_try)
            err_c, h_acc, h_rej, slow = controller.radau_step_sizes(
                hh, err, finite, err_old, h_old, first, iters, theta, max_iter, expo
            )

            if any_(accept):  # accepted samples advance
                kernel.advance(accept, tcur, h_step)
                tcur = pick(accept, tcur + h_step, tcur)
                reached = accept & to_stop
                tcur = where(reached, t_stop, tcur)
                prev_h = pick(accept, h_step, prev_h)
                have_prev |= accept
                h_old = pick(accept, hh, h_old)
                err_old = pick(accept, ops.maximum(err_c, 1e-2), err_old)
                need_jac |= accept & slow
                fresh &= not_(accept)
                first &= not_(accept)
                n_steps += accept
                if not ode:  # periodic index check (Theorem 9) with a fresh Jacobian
                    need_jac |= accept & (n_steps % index_check_every == 0)
            rejected_last = not_(accept) & (rejected_last | reject)
            h = ops.steps(where(accept, h_acc, where(reject, h_rej, h)))
            active &= not_(accept & (tcur >= t_end))
            if any_(accept):  # past a stop: the next one; a step cut short there keeps its plan
                restart = reached & active
                h = where(restart, ops.maximum(h, h_planned), h)
                next_stop = where(restart, next_stop + 1, next_stop)
                if any_(restart):  # the input may jump here: no history carried across
                    if not ode:
                        kernel.restart(restart, tcur)
                    h_old = where(restart, 0.0, h_old)
                    err_old = where(restart, 1.0, err_old)
                    have_prev &= not_(restart)

    records = kernel.records()
    status = np.array(ops.host(status, np.int8))
    records.stop = stop_times(status, ops.host(tcur))
    if core.system.m:
        x_out, z_out = _outputs_with_consistent_z(core, records, t, status, messages)
    else:
        x_out, z_out = records.evaluate(t)

    def dev(a, dtype):
        return torch.from_numpy(ops.host(a, dtype)).to(x0.device).reshape(batch)

    return dict(
        x=x_out,
        z=z_out,
        status=torch.from_numpy(status).to(x0.device).reshape(batch),
        messages=messages,
        n_steps=dev(n_steps, np.int64),
        n_rejected=dev(n_rej, np.int64),
        n_newton=dev(n_newton, np.int64),
        n_jac=kernel.n_jac,
        n_lu=kernel.n_lu,
        n_f=core.n_f_evals,
        records=records,
    )


def _outputs_with_consistent_z(core, records, t, status, messages):
    """``(x, z)`` (*batch, T, n), (*batch, T, m) at the output times ``t`` (T,), with ``z`` at
    the times inside a step solved from the algebraic equations at the interpolated ``x``
    (:meth:`~integrators._irk_system.StageSystem.algebraic_states`, from the interpolated
    ``z`` and ``x'``): the error estimate controls the stage values, which solve them, not the
    stage polynomial of ``z`` between its nodes. A sample whose solve fails at an output time
    stops before it (``status`` and ``messages`` updated in place, NaN from there on)."""
    x, z, inside, xdot = records.evaluate(t, interior=True)
    live = inside & torch.isfinite(x).all(-1)  # (*batch, T)
    columns = torch.nonzero(live.reshape(-1, t.shape[0]).any(0)).flatten().tolist()
    stop = np.full(status.shape, np.inf)
    values = list(z.unbind(-2))
    for k in columns:
        here = live[..., k, None]  # the others (stopped: NaN) solve at zeros, result unused
        x_k, z_k, xdot_k = (torch.where(here, v[..., k, :], 0.0) for v in (x, z, xdot))
        _, z_k, res = core.system.algebraic_states(t[k], x_k, z_k, core.signal.at(t[k]), xdot_k)
        solved = res.converged.reshape(live.shape[:-1]) & live[..., k]
        values[k] = torch.where(solved[..., None], z_k, values[k])
        failed = to_host(live[..., k] & ~solved, status.shape) & (status == 0)
        stop = np.where(failed & np.isinf(stop), float(t[k - 1]), stop)
        for idx in np.argwhere(failed).tolist():
            messages.append(
                f"sample {tuple(idx)}: the algebraic equations did not converge for z at the "
                f"output time t = {float(t[k]):.6g}; its outputs from there on are NaN."
            )
        status[failed] = int(Status.NEWTON_FAILED)
    z = torch.stack(values, -2)
    if np.isfinite(stop).any():
        records.stop = np.minimum(records.stop, stop)
        x, z = nan_beyond(x, t, stop), nan_beyond(z, t, stop)
    return x, z


class TorchKernel:
    """:class:`RadauKernel` on torch tensors (*batch, ...) on the device of ``x0``: every
    system kind (explicit and implicit ODEs, semi-explicit DAEs with their index check), the
    Newton solve of :meth:`IRKCore.newton` and the factorisations of
    :class:`~integrators._irk_core.IterationMatrix`. The stages of each step that moves a
    sample carry the implicit-function-theorem gradient (:meth:`IRKCore.ift`). Each step
    needs one device-to-host transfer of the error norms (plus one per Newton iteration); the
    step-size control costs no device kernels."""

    scalar = False

    def __init__(self, core, x0, z0, xdot0, t, rtol, atol, newton_tol, max_iter, index_tol):
        self.core, self.x0, self.z0 = core, x0, z0
        self.batch = x0.shape[:-1]
        self.hshape = host_shape(self.batch)
        self.dtype = x0.dtype
        self.hdt = np.float64 if x0.dtype == torch.float64 else np.float32
        n, m, s = core.system.n, core.system.m, core.s
        self.gamma, e_np = embedded_weights(core.tab)
        self.gamma_e = torch.as_tensor(self.gamma * e_np, dtype=x0.dtype, device=x0.device)
        self.rms = 1.0 / (n + m) ** 0.5
        self.c = np.array(core.c)
        self.c_col = self.c.reshape(s, *([1] * max(len(self.batch), 1)))
        self.rtol, self.atol, self.newton_tol, self.max_iter = rtol, atol, newton_tol, max_iter
        self.x, self.z, self.xdot = x0, z0, xdot0
        self.prev_W = None
        self.mat = IterationMatrix(core, index_tol)
        core.solver.want_real_block = True  # the error filter solves with the real block
        self.rec = StepRecords(core.tab, n)
        dummy_W = torch.cat([torch.zeros_like(x0), z0], -1)[..., None, :]
        dummy_W = dummy_W.expand(*self.batch, s, n + m)
        t0 = np.full(self.batch, to_host(t[0]), dtype=self.hdt)
        self.rec.append(t0, np.ones(self.batch, dtype=self.hdt), x0, dummy_W, z0)

    @property
    def n_jac(self) -> int:
        return self.mat.n_jac

    @property
    def n_lu(self) -> int:
        return self.mat.n_lu

    def begin_step(self, tcur, h):
        core, s, batch = self.core, self.core.s, self.batch
        # one transfer: t_k, h, t_k + h and the stage times t_k + c_i h, each (*batch,)
        host = np.empty((3 + s, *self.hshape), dtype=self.hdt)
        host[0], host[1], host[2], host[3:] = tcur, h, tcur + h, tcur + self.c_col * h
        on_dev = to_device(host, self.x0, self.dtype, shape=(3 + s, *batch))[..., None]
        self.tcol, self.h_t, self.t_next = on_dev[0], on_dev[1, ..., 0], on_dev[2]
        self.xd, self.zd = self.x.detach(), self.z.detach()
        self.times = core.stage_times(
            self.tcol, self.h_t[..., None], len(batch), stacked=on_dev[3:]
        )
        self.inputs = core.stage_inputs(self.times, self.tcol)
        self.sc_x = self.atol + self.rtol * self.xd.abs()
        self.sc_z = self.atol + self.rtol * self.zd.abs() if core.system.m else self.zd

    def jacobian(self, mask):
        return self.mat.update_jacobian(mask, self.tcol, self.xd, self.zd, self.xdot.detach())

    def factorize(self, mask, h, h_fact):
        h_lu = np.where(mask, h, np.where(h_fact > 0, h_fact, h))
        return self.mat.update_factors(mask, to_device(h_lu, self.x0, self.dtype, self.batch))

    def newton(self, live, have_prev, ratio):
        s = self.core.s
        W0 = _stage_guess(self.c, self.prev_W, have_prev, ratio, self.xdot.detach(), self.zd, s)
        self.W, conv, iters, theta, nonfin = self.core.newton(
            self.times,
            self.inputs,
            self.h_t,
            self.xd,
            W0,
            self.mat.factors,
            self.sc_x,
            self.sc_z,
            self.newton_tol,
            self.max_iter,
            live,
        )
        return conv, iters, theta, nonfin

    def error(self, ok, retry):
        """The scaled norm of the filtered embedded error estimate (module docstring), the
        ``retry`` samples' estimate refined by one more ``f`` evaluation (explicit ODEs)."""
        core, mat, W, atol, rtol = self.core, self.mat, self.W, self.atol, self.rtol
        n, m = core.system.n, core.system.m
        ode = core.system.kind == "ode"
        self.Wg = core.ift(self.times, self.inputs, self.h_t, self.x, W, valid=ok)
        self.x_new = core.step_end(self.x, self.h_t, self.Wg)
        with torch.no_grad():
            eK = self.gamma_e @ (W[..., :n] if m else W)
            rhs = self.xdot + eK
            if not ode:  # M = dR/dK (the identity for explicit ODEs)
                rhs = (mat.E[..., :, :n] @ rhs[..., None])[..., 0]
            sol = core.solver.solve_real_block(mat.factors, rhs)
            sc = torch.maximum(self.sc_x, atol + rtol * self.x_new.detach().abs())
            err_x = sol[..., :n] if m else sol
            if ode and retry.any():
                core.n_f_evals += 1
                tcol = self.tcol
                f_err = core.system.rhs_f(tcol, self.xd + err_x, self.zd, core.signal.at(tcol))
                sol2 = core.solver.solve_real_block(mat.factors, f_err + eK)
                err_x = masked_update(retry, sol2, err_x)
            err = torch.linalg.vector_norm(err_x / sc, dim=-1)
            if m:
                sc_z = atol + rtol * torch.maximum(self.zd.abs(), W[..., -1, n:].abs())
                err_z = (self.gamma / self.h_t)[..., None] * sol[..., n:]
                err = torch.hypot(err, torch.linalg.vector_norm(err_z / sc_z, dim=-1))
        finite_x = torch.isfinite(self.x_new.detach()).all(-1).to(err.dtype)
        both = to_host(torch.stack([err, finite_x]), (2, *self.hshape)).astype(np.float64)
        err, finite_x = both[0] * self.rms, both[1]
        finite = (finite_x > 0) & np.isfinite(err)
        return np.where(finite, err, np.inf), finite

    def advance(self, accept, tcur, h):
        core, n, m = self.core, self.core.system.n, self.core.system.m
        t0 = np.where(accept, tcur, np.inf).astype(self.hdt)
        self.rec.append(t0.reshape(self.batch), h.reshape(self.batch), self.x, self.Wg, self.z)
        if core.system.kind == "ode":  # x' at the step end: f for explicit ODEs, else K_s
            core.n_f_evals += 1
            with torch.no_grad():
                t = self.t_next
                xdot_new = core.system.rhs_f(t, self.x_new.detach(), self.z, core.signal.at(t))
        else:
            xdot_new = self.W[..., -1, :n].detach()
        self.x = masked_update(accept, self.x_new, self.x)
        self.z = masked_update(accept, self.Wg[..., -1, n:], self.z) if m else self.z
        self.xdot = masked_update(accept, xdot_new, self.xdot)
        self.prev_W = self.W if self.prev_W is None else masked_update(accept, self.W, self.prev_W)

    def restart(self, mask, tcur):
        core = self.core
        t = to_device(np.asarray(tcur, dtype=self.hdt), self.x0, self.dtype, shape=self.batch)
        t = t[..., None]
        with torch.no_grad():
            xdot, _, res = core.system.algebraic_states(
                t, self.x.detach(), self.z.detach(), core.signal.at(t), self.xdot
            )
        solved = mask & to_host(res.converged, self.hshape)  # the others keep their guesses
        self.xdot = masked_update(solved, xdot, self.xdot)

    def escaping(self):
        return escaping(self.x, self.z, self.x0, self.z0, self.hshape)

    def records(self):
        return self.rec

    def step_mode(self):
        return contextlib.nullcontext()  # the stages carry the IFT gradient


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


def _first_step(core, x0, z0, xdot0, t0, span, rtol, atol, s, dt0):
    """(*batch,) first step: ``dt0``, or :func:`~integrators.controllers.initial_step` with
    the embedded estimate's order ``s`` (an explicit Euler probe of ``f`` for ODEs)."""
    if dt0 is not None:
        return torch.full(x0.shape[:-1], float(dt0), dtype=x0.dtype, device=x0.device)

    def probe(tt, x):
        core.n_f_evals += 1
        t1 = tt[..., None]
        return core.system.rhs_f(t1, x, z0, core.signal.at(t1))

    rhs = probe if core.system.kind == "ode" else None
    return initial_step(rhs, t0, x0.detach(), xdot0, s, rtol, atol, span)


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
