"""Adaptive embedded explicit Runge-Kutta with per-sample step sizes (notes §6.5).

Each trial step computes the stages of the tableau once and two solutions from them,
``x_{k+1} = x_k + dt sum_i b_i K_i`` and ``xhat_{k+1} = x_k + dt sum_i bhat_i K_i``
(notes eq. 6.44a-b); their difference is the local error estimate that the step-size
controller (:mod:`integrators.controllers`) turns into accept/reject and the next step.
For first-same-as-last tableaus such as Dormand-Prince 5(4) the last stage of an accepted
step is ``K_1`` of the next one (notes eq. 6.45), so a step costs ``s - 1`` evaluations.

Batching: every sample of the batch has its own time, step size, error norm, decision and
counters. The batch is advanced together, one batched ``rhs`` call per stage with the
per-sample stage times passed as a ``(*batch, 1)`` tensor (inputs bound to the model, see
:mod:`integrators.inputs`); a sample that has
finished (or failed) takes steps of size zero and its state is frozen, so its answer and its
step count are exactly those of solving it alone.

Output: the steps are not shortened to hit the requested times. Each accepted step keeps the
coefficients of its continuous extension (:mod:`integrators.dense`), and the requested times,
as well as any time passed to ``Solution.at``, are evaluated from them with a batched
``searchsorted`` over each sample's accepted-step grid.

Sampled inputs (:attr:`integrators.inputs.BoundRHS.breakpoints`): the input jumps (zero-order
hold) or kinks (linear interpolation) at its sample times, where neither the Runge-Kutta
solution nor its error estimate is smooth. Steps then end at every sample time (a step cut
short there does not shrink the next one), the held input of a step's interval is used up to
and including its right end (eq. 8.34), and after a jump ``K_1`` is evaluated again with the
next sample.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ._options import (
    broadcast_tolerance,
    check_int,
    check_state_dtype,
    check_tolerances,
    raise_shape_change,
    refuse_time_gradient,
)
from .controllers import IController, PIController, error_norm, initial_step
from .dense import continuous_extension
from .errors import InputValidationError
from .inputs import BoundRHS
from .solution import Solution, SolverStats, Status
from .tableau import ButcherTableau, tableau

_DEFAULT_CHECK_EVERY = 8  # host synchronisations ("is every sample done?") every N steps


def _as_dt0(dt0, batch_shape, dtype, device):
    dt0 = torch.as_tensor(dt0, dtype=dtype, device=device).detach()
    if torch.any(~torch.isfinite(dt0)) or torch.any(dt0 <= 0):
        raise InputValidationError(f"dt0 must be positive and finite, got {dt0}.")
    try:
        return dt0.expand(batch_shape).reshape(-1).clone()
    except RuntimeError as exc:
        raise InputValidationError(
            f"dt0 of shape {tuple(dt0.shape)} must be a scalar or broadcast to the batch "
            f"shape {tuple(batch_shape)}."
        ) from exc


def _sample_label(flat_index: int, batch_shape) -> str:
    if len(batch_shape) <= 1:
        return f"sample {flat_index}"
    return f"sample {tuple(int(i) for i in np.unravel_index(flat_index, tuple(batch_shape)))}"


class _StepRecord:
    """Per-step dense-output data of all samples, stacked along a step axis at the end.

    For record j of sample b the interpolant is, with ``theta = (s - start) / h``,
    ``x(s) = x + theta (r_1 + theta (r_2 + theta (r_3 + theta r_4)))`` on
    ``[start, start + h]``. Rejected attempts and finished samples get ``h = 0`` and ``r = 0``
    (a constant piece, whatever ``r`` holds), so each sample's start times are non-decreasing
    and the last record with ``start <= s`` always holds the right piece.
    """

    def __init__(self):
        self.steps = []  # (start, h, x, r) of each step: (B,), (B,), (B, nx), (B, nx, 4)

    def append(self, start, h, x, r):
        self.steps.append((start, h, x, r))

    def interpolant(self, t_reached, failed, dead, batch_shape):
        # start, h (B, N), xs (B, N, nx), rs (B, N, nx, 4)
        start, h, xs, rs = (torch.stack(v, dim=1) for v in zip(*self.steps, strict=True))
        B, _, nx = xs.shape

        def evaluate(s: torch.Tensor) -> torch.Tensor:
            """States at times ``s`` (M,) inside [t0, t_end] (``Solution.at`` checks them)."""
            s = s.to(dtype=start.dtype, device=start.device).detach().reshape(-1)
            M = s.numel()
            query = s.expand(B, M).contiguous()
            idx = (torch.searchsorted(start, query, right=True) - 1).clamp_min(0)
            t_k = start.gather(1, idx)
            h_k = h.gather(1, idx)
            moving = h_k > 0
            theta = torch.where(moving, (query - t_k) / torch.where(moving, h_k, 1.0), 0.0)
            theta = theta.clamp(0.0, 1.0).unsqueeze(-1)  # (B, M, 1)
            x_k = xs.gather(1, idx.unsqueeze(-1).expand(B, M, nx))
            r_k = rs.gather(1, idx[..., None, None].expand(B, M, nx, 4))
            poly = r_k[..., 3]
            for m in (2, 1, 0):
                poly = r_k[..., m] + theta * poly
            # constant pieces (rejected trials) may hold non-finite r: select, not multiply
            out = torch.where(moving.unsqueeze(-1), x_k + theta * poly, x_k)
            beyond = (failed[:, None] & (query > t_reached[:, None])) | dead[:, None]
            out = torch.where(beyond.unsqueeze(-1), torch.full_like(out, math.nan), out)
            return out.reshape(*batch_shape, M, nx)

        return evaluate


def solve_adaptive(
    rhs,
    x0: torch.Tensor,
    t: torch.Tensor,
    tab: ButcherTableau | None = None,
    *,
    rtol=1e-6,
    atol=1e-9,
    controller: IController | None = None,
    dt0=None,
    max_steps: int = 100_000,
    check_every: int = _DEFAULT_CHECK_EVERY,
) -> Solution:
    """Integrate ``x' = rhs(t, x)`` with an embedded explicit Runge-Kutta pair, per sample.

    Args:
        rhs: ``rhs(t, x) -> (*batch, nx)`` with ``t`` a (*batch, 1) tensor of per-sample times
            (an input bound to the model, e.g. by :func:`integrators.inputs.bind_rhs`).
        x0: (*batch, nx) initial states (at ``t[0]``).
        t: (T,) strictly increasing output times; the states are reported there by dense
            output, the steps are not shortened to hit them (unless an input is sampled on
            them, see the module docstring).
        tab: explicit tableau with embedded weights ``b_err``; Dormand-Prince 5(4) when None.
        rtol, atol: relative and absolute tolerances of the error norm
            (:func:`integrators.controllers.error_norm`): floats, or tensors broadcastable to
            (*batch, nx).
        controller: :class:`~integrators.controllers.IController` or
            :class:`~integrators.controllers.PIController` (the default,
            ``PIController()``).
        dt0: first trial step, a float or a (*batch,) tensor; chosen per sample from
            ``f(x0)`` and one Euler probe when None (:func:`controllers.initial_step`).
        max_steps: maximum number of step attempts (accepted plus rejected) per sample.
        check_every: the loop asks the device whether every sample is done only every
            ``check_every`` steps (finished samples just take zero steps meanwhile).

    A trial step whose error norm is not finite (inf/nan in a stage or the new state) is
    rejected like any other and retried with ``min_factor`` times the step; only if the step
    then shrinks below the time resolution does the sample stop, as NON_FINITE (or as
    STEP_TOO_SMALL when the last trial was finite, e.g. at a finite escape time).

    Returns:
        :class:`Solution` with ``x`` (*batch, T, nx), per-sample ``status`` (SUCCESS,
        MAX_STEPS, NON_FINITE or STEP_TOO_SMALL, with a message naming the sample and the
        time it reached; its outputs beyond that time are NaN), ``stats`` with per-sample
        ``n_steps``, ``n_rejected``, ``n_f_evals`` tensors and batch totals in
        ``stats.extra`` (``n_rhs_calls``: batched right-hand-side calls, ``n_iterations``:
        batched step attempts, ``t_reached``: (*batch,) final times), and ``interpolant`` for
        ``Solution.at``. Differentiable by backpropagation through the accepted steps; the
        step sizes are computed from detached values.

    Raises:
        InputValidationError: a tableau without embedded weights or not explicit, bad
            tolerances (:func:`integrators._options.check_tolerances`), a controller that
            is not an IController or PIController instance, ``dt0`` or
            ``max_steps``, a state dtype other than float32/float64, output times ``t`` that
            require grad (not differentiated here), or an rhs returning the wrong shape.
    """
    tab = tableau("dopri5") if tab is None else tab
    if tab.b_err is None or not tab.is_explicit:
        raise InputValidationError(
            f"solve_adaptive needs an explicit tableau with embedded weights b_err; "
            f"{tab!r} is not one. Use tableau('dopri5') or pass b_err."
        )
    max_steps = check_int(max_steps, "max_steps")
    check_every = check_int(check_every, "check_every")
    check_state_dtype(x0.dtype)
    check_tolerances(rtol, atol, x0.dtype)
    refuse_time_gradient(t, tab.name)
    controller = PIController() if controller is None else controller
    if not isinstance(controller, IController):
        raise InputValidationError(
            f"the controller of an embedded explicit pair ({tab.name!r}) must be an "
            f"IController or PIController instance (integrators.controllers), got "
            f"{controller!r}; GustafssonController is Radau IIA's predictive rule."
        )

    dtype, device = x0.dtype, x0.device
    batch_shape = tuple(x0.shape[:-1])
    nx = x0.shape[-1]
    B = int(np.prod(batch_shape)) if batch_shape else 1
    hint = ", the states' shape."
    rtol = broadcast_tolerance(rtol, "rtol", x0.shape, x0, hint)
    atol = broadcast_tolerance(atol, "atol", x0.shape, x0, hint)
    # tensors in the flat (B, nx) layout of the solver
    rtol, atol = (v if isinstance(v, float) else v.reshape(-1, nx) for v in (rtol, atol))

    t_out = t.detach().to(dtype=dtype, device=device)
    t0, t_end = float(t_out[0]), float(t_out[-1])
    span = t_end - t0
    dt_min = 16.0 * torch.finfo(dtype).eps * max(abs(t0), abs(t_end), span)
    # the times where steps end: the input's breakpoints inside (t0, t_end), and t_end
    breaks = rhs.breakpoints if isinstance(rhs, BoundRHS) else None
    stops = t_out[[0, -1]]
    if breaks is not None:
        grid = breaks.detach().to(dtype=dtype, device=device)
        stops = torch.cat([stops[:1], grid[(grid > t0) & (grid < t_end)], stops[1:]])
    last_stop = stops.shape[0] - 1
    held = isinstance(rhs, BoundRHS) and rhs.kind == "zoh"  # K_1 again after every jump

    def held_sample(t_flat):
        """The (B,) index of the sample a zero-order hold gives from ``t_flat`` on."""
        return (torch.searchsorted(grid, t_flat, right=True) - 1).clamp(0, grid.shape[0] - 1)

    ext = continuous_extension(tab)
    s = tab.stages
    A, b, c, e = tab.tensors(dtype, device)
    n_ext = s + 1 if ext.extra_eval else s
    e_ext = torch.zeros(n_ext, dtype=dtype, device=device)
    e_ext[:s] = e
    # one matmul gives the error estimate and the four dense-output coefficient vectors
    combine = torch.cat([e_ext[:, None], ext.tensor(dtype, device)], dim=1)  # (n_ext, 5)
    q = min(tab.order, tab.embedded_order)
    evals_per_attempt = s if ext.extra_eval else s - 1
    c_list = [float(v) for v in tab.c]
    a_rows = [A[i, :i].contiguous() for i in range(s)]
    b_vec = b.contiguous()

    n_calls = 0

    def call(t_flat, x_flat, sample=None):
        """``rhs`` at (B,) times and (B, nx) states; a zero-order hold gives the (B,) held
        ``sample``."""
        nonlocal n_calls
        n_calls += 1
        x_call = x_flat.reshape(*batch_shape, nx)
        t_call = t_flat.reshape(*batch_shape, 1)
        if held:
            out = rhs(t_call, x_call, interval=sample.reshape(*batch_shape, 1))
        else:
            out = rhs(t_call, x_call)
        if out.shape != x_call.shape:
            raise_shape_change(out, x_call, t_flat)
        return out.reshape(B, nx)

    x = x0.reshape(B, nx)
    t_cur = torch.full((B,), t0, dtype=dtype, device=device)
    k_cur = torch.zeros(B, dtype=torch.int64, device=device)  # the stop before t_cur
    sample = held_sample(t_cur) if held else None
    k1 = call(t_cur, x, sample)
    finite0 = torch.isfinite(x).all(-1) & torch.isfinite(k1).all(-1)
    # a sample that is non-finite at t0 is frozen at zeros so that it poisons nothing
    if not bool(finite0.all()):
        x = torch.where(finite0[:, None], x, 0.0)
        k1 = torch.where(finite0[:, None], k1, 0.0)
    # step sizes are not differentiated: initial_step runs under no_grad, dt0 is detached
    if dt0 is None:
        h_next = initial_step(
            lambda tt, xx: call(tt, xx, sample),
            t_cur,
            x.detach(),
            k1.detach(),
            q,
            rtol,
            atol,
            span,
        )
    else:
        h_next = _as_dt0(dt0, batch_shape, dtype, device).clamp_max(span)
    init_evals = 2 if dt0 is None else 1  # f(t0, x0), plus the probe of initial_step

    status = torch.where(finite0, Status.SUCCESS, Status.NON_FINITE).to(torch.int8)
    active = finite0.clone()
    err_prev = torch.ones(B, dtype=dtype, device=device)
    after_reject = torch.zeros(B, dtype=torch.bool, device=device)
    last_nonfinite = torch.zeros(B, dtype=torch.bool, device=device)
    n_acc = torch.zeros(B, dtype=torch.int64, device=device)
    n_att = torch.zeros(B, dtype=torch.int64, device=device)
    n_restarts = torch.zeros(B, dtype=torch.int64, device=device)  # K_1 after an input jump
    records = _StepRecord()
    code_non_finite, code_too_small, code_max_steps = (
        torch.tensor(int(code), dtype=torch.int8, device=device)
        for code in (Status.NON_FINITE, Status.STEP_TOO_SMALL, Status.MAX_STEPS)
    )
    zero_r = torch.zeros(B, nx, 4, dtype=dtype, device=device)
    iteration = 0

    while True:
        if iteration % check_every == 0 and not bool(active.any()):
            break
        iteration += 1
        with torch.no_grad():
            t_stop = stops[k_cur + 1]
            remaining = t_stop - t_cur
            # a trial that would leave less than dt_min before the next stop goes all the way
            last = h_next + dt_min >= remaining
            # a step ends at a float time, and the state moves by exactly its length
            h = torch.where(last, remaining, (t_cur + h_next) - t_cur) * active
        hc = h[:, None]
        stages = [k1]
        x_stage = x
        for i in range(1, s):
            x_stage = torch.addcmul(x, hc, torch.stack(stages, -1) @ a_rows[i])
            stages.append(call(torch.add(t_cur, h, alpha=c_list[i]), x_stage, sample))
        if tab.is_fsal:
            x_new, f_new = x_stage, stages[-1]
        else:
            x_new = torch.addcmul(x, hc, torch.stack(stages, -1) @ b_vec)
            f_new = call(t_cur + h, x_new, sample)
            stages.append(f_new)
        combined = torch.stack(stages, -1) @ combine  # (B, nx, 5)
        r = combined[..., 1:] * hc[..., None]  # (B, nx, 4)

        with torch.no_grad():
            err = combined[..., 0].detach() * hc
            norm = error_norm(err, x.detach(), x_new.detach(), rtol, atol)
            finite = torch.isfinite(norm)
            accept, h_prop = controller.propose(norm, err_prev, h, q, after_reject)
            accept = accept & active & finite
            n_att += active
            n_acc += accept
            err_prev = torch.where(accept, norm, err_prev)
            after_reject = active & ~accept
            last_nonfinite = active & ~finite
            stopped = accept & last
            t_next = torch.where(accept, torch.where(last, t_stop, t_cur + h), t_cur)
            still = active & ~(stopped & (k_cur + 1 == last_stop))
            too_small = still & (h_prop < dt_min)
            out_of_steps = still & ~too_small & (n_att >= max_steps)
            status = torch.where(
                too_small, torch.where(last_nonfinite, code_non_finite, code_too_small), status
            )
            status = torch.where(out_of_steps, code_max_steps, status)
            active = still & ~too_small & ~out_of_steps
            # a step cut short at a stop keeps the planned size for the next one
            h_next = torch.where(stopped, torch.maximum(h_prop, h_next), h_prop)
            k_next = torch.where(stopped & still, k_cur + 1, k_cur)

        acc_col = accept[:, None]
        records.append(t_cur, h * accept, x, r)
        x = torch.where(acc_col, x_new, x)
        k1 = torch.where(acc_col, f_new, k1)
        if held:  # K_1 with the sample held from a stop on, where a member reached one
            sample = held_sample(t_next)
            crossed = k_next != k_cur
            # skipped where no member crossed: a free check on the host; on a device it
            # would synchronise every attempt, which the loop avoids (see check_every)
            if x.device.type != "cpu" or bool(crossed.any()):
                k1 = torch.where(crossed[:, None], call(t_next, x, sample), k1)
                n_restarts += crossed
        t_cur, k_cur = t_next, k_next

    records.append(t_cur, torch.zeros_like(t_cur), x, zero_r)
    failed = status != Status.SUCCESS
    interpolant = records.interpolant(t_cur, failed, ~finite0, batch_shape)
    x_out = interpolant(t_out)

    messages = _messages(status, t_cur, ~finite0, max_steps, batch_shape)
    n_f = init_evals + evals_per_attempt * n_att + n_restarts
    stats = SolverStats(
        n_f_evals=n_f.reshape(batch_shape),
        n_steps=n_acc.reshape(batch_shape),
        n_rejected=(n_att - n_acc).reshape(batch_shape),
        extra={
            "n_rhs_calls": n_calls,
            "n_iterations": iteration,
            "t_reached": t_cur.reshape(batch_shape),
            "controller": repr(controller),
        },
    )
    return Solution(
        t=t_out,
        x=x_out,
        status=status.reshape(batch_shape),
        stats=stats,
        messages=messages,
        method=tab.name,
        interpolant=interpolant,
    )


def _messages(status, t_reached, dead_at_start, max_steps, batch_shape):
    """One line per failed sample (one host synchronisation)."""
    codes = status.cpu().numpy()
    dead = dead_at_start.cpu().numpy()
    bad = np.nonzero(codes != Status.SUCCESS)[0]
    if bad.size == 0:
        return []
    times = t_reached.detach().cpu().numpy()
    out = []
    for i in bad:
        who = _sample_label(int(i), batch_shape)
        code = Status(int(codes[i]))
        when = float(times[i])
        if code == Status.MAX_STEPS:
            out.append(
                f"{who}: MAX_STEPS, {max_steps} step attempts used before reaching the final "
                f"time; stopped at t = {when:.10g}. Raise max_steps, loosen rtol/atol, or use "
                "an implicit method if the problem is stiff."
            )
        elif code == Status.NON_FINITE and dead[i]:
            out.append(
                f"{who}: NON_FINITE, the initial state or f(t0, x0) is inf/nan at "
                f"t = {when:.10g}; all its outputs are NaN. Check x0 and the model there."
            )
        elif code == Status.NON_FINITE:
            out.append(
                f"{who}: NON_FINITE, the state or f became inf/nan in every trial step after "
                f"t = {when:.10g} and the step size shrank to nothing. Check the model for a "
                "finite escape time or a division by zero there."
            )
        else:
            out.append(
                f"{who}: STEP_TOO_SMALL, the step size fell below the time resolution at "
                f"t = {when:.10g}; the solution may blow up there (finite escape time) or the "
                "problem is very stiff (use an implicit method)."
            )
    return out
