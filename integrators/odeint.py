"""``odeint``: validate, bind the input, dispatch to a solver.

The method is resolved by :func:`integrators.methods.resolve_method`, and the kind of its run
(:func:`integrators.methods.run_kind`) picks the solver:

* an explicit tableau without ``b_err`` (``"euler"`` ... ``"rk38"``), or any explicit tableau
  with ``adaptive=False``: fixed-step explicit RK (:func:`integrators.explicit.solve_explicit`);
* ``"dopri5"`` or any explicit tableau with ``b_err``: adaptive step control
  (``integrators.adaptive.solve_adaptive``);
* ``"gauss_legendre"``, ``"radau_iia"`` (with ``stages=``), ``"implicit_euler"``,
  ``"implicit_midpoint"`` or an implicit tableau: ``integrators.implicit.solve_implicit_ode``;
* ``"auto"``: ``integrators.auto.choose_method`` picks one of the above; the choice is recorded
  in ``sol.stats.extra["auto"]``.

Options left at ``None`` take the values of :data:`DEFAULTS`; an option given for a kind of run
it does not apply to (:data:`integrators.methods.OPTION_KINDS`) raises
:class:`InputValidationError` naming the method and the option. The adaptive, implicit and
automatic solvers are imported only when used.
"""

from __future__ import annotations

import torch

from ._options import (
    check_flag,
    check_int,
    check_positive,
    check_state,
    check_times,
    check_tolerances,
    first_nonfinite,
)
from .errors import InputValidationError
from .explicit import solve_explicit
from .inputs import bind_rhs
from .methods import (
    AUTO,
    EXPLICIT_ADAPTIVE,
    IMPLICIT_ADAPTIVE,
    IMPLICIT_FIXED,
    METHOD_NAMES,
    OPTION_KINDS,
    Method,
    resolve_method,
    run_kind,
)
from .solution import Solution

__all__ = ["METHOD_NAMES", "odeint"]

#: The values of the options a call leaves at None.
DEFAULTS = dict(
    substeps=1,
    rtol=1e-6,
    atol=1e-9,
    max_steps=100_000,
    compile="auto",
    checkpoint=False,
)


def odeint(
    f,
    x0,
    t,
    *,
    method="rk4",
    u=None,
    interpolation="zoh",
    substeps=None,
    rtol=None,
    atol=None,
    controller=None,
    dt0=None,
    max_steps=None,
    stages=None,
    compile=None,
    checkpoint=None,
    **kwargs,
) -> Solution:
    """Simulate ``x' = f(t, x[, u])`` from ``x0`` and report the states at the times ``t``.

    Args:
        f: ``f(t, x) -> (*batch, nx)`` when ``u is None``, else ``f(t, x, u)``. ``t`` is a
            0-dim tensor (fixed-step solvers) or a (*batch, 1) tensor (adaptive solvers).
            An ``nn.Module`` works directly; its parameters receive gradients. If ``f``
            broadcasts ``x0`` to a larger batch (e.g. a parameter of shape (B, 1)), ``x0``
            is expanded to that batch; so it is to the batch of a sampled input ``u``.
        x0: (*batch, nx) initial states; array-likes become float64 tensors.
        t: (T,) strictly increasing output times, T >= 2 (converted to x0's dtype/device).
        method: a name from :data:`METHOD_NAMES` or a :class:`ButcherTableau`
            (:mod:`integrators.methods`).
        u: None, a callable ``u(t)``, or samples (T, nu) / (*batch, T, nu) on ``t``
            (see :func:`integrators.inputs.bind_rhs`).
        interpolation: ``"zoh"`` (notes eq. 8.34) or ``"linear"`` for sampled ``u``.
        substeps: fixed-step methods: integer number of steps per output interval (1).
        rtol, atol: tolerances (1e-6, 1e-9) of adaptive methods (and the Newton scale
            ``atol + rtol |x|`` of implicit ones): numbers or tensors, ``atol >= 0`` and
            ``rtol`` at least :data:`integrators._options.RTOL_MIN_EPS` machine epsilons of
            the state dtype (8.9e-16 in float64, 4.8e-7 in float32).
        controller, dt0, max_steps: adaptive step control: ``controller`` an
            :class:`~integrators.controllers.IController` or ``PIController`` (default of
            dopri5) or ``GustafssonController`` (default of Radau IIA), ``max_steps`` step
            attempts per sample (100 000), ``dt0`` the first trial step (> 0; a longer one is
            cut to the span); adaptive methods only.
        stages: number of stages of ``"gauss_legendre"`` / ``"radau_iia"`` (those only).
            Adaptive runs control the error per step, so the global error of an order-``p``
            method falls like ``rtol ** (p / (p + 1))``: for the first-order ``radau_iia``
            with ``stages=1`` (implicit Euler) like ``sqrt(rtol)`` (on x' = -x over 3 s,
            155 rtol at ``rtol=1e-6``, 1550 rtol at 1e-8); ``stages=3`` (order 5, the
            default) stays below ``rtol`` there.
        compile: fixed-step explicit methods: ``True``, ``False`` or ``"auto"`` (default; see
            :func:`integrators.explicit.solve_explicit`).
        checkpoint: fixed-step explicit methods with autograd: ``True`` recomputes the graph
            in segments of about ``sqrt(n_steps)`` steps during the backward pass (memory
            about the square root of the run's length, about twice the compute), an integer
            sets the steps per segment, ``False`` keeps every step's graph (see
            :func:`integrators.explicit.solve_explicit`).
        **kwargs: ``adaptive`` (``True``, ``False`` or ``None``: the method's default);
            ``adaptive=False`` runs an embedded pair (e.g. dopri5) at fixed step; other
            keywords go to the implicit solver (Newton options, see
            :func:`integrators.implicit.solve_implicit_ode`). With ``method="auto"`` they
            are checked whatever is picked and left unused when dopri5 is (listed in
            ``stats.extra["auto"]["unused_options"]``).

    Gradients reach ``x0`` and the model's parameters with every method. Gradients with
    respect to the output times ``t`` are supported by the fixed-step explicit methods (the
    derivative of the discrete map: the step grid follows ``t``); other methods raise
    :class:`InputValidationError` when ``t`` requires grad.

    An empty batch (``x0`` of shape (0, nx), or any zero batch dimension) gives an empty
    :class:`Solution` of the right shapes with every method.

    Returns:
        :class:`Solution` with ``x`` of shape (*batch, T, nx), per-sample status, stats.

    Raises:
        InputValidationError: wrong shapes of ``x0``, ``t``, ``u`` or of ``f``'s output
            (checked at ``(t0, x0)`` and, by every solver, at each later evaluation);
            non-finite ``x0``, ``t``, ``u`` or ``f(t0, x0)``; ``t`` not strictly increasing;
            a state dtype other than float32/float64; bad ``substeps``, ``max_steps``,
            ``dt0``, ``stages`` or tolerances; non-bool flags (``adaptive``, ``compile``,
            ``host_loop``); options the chosen method does not use; unexpected keywords;
            ``t`` requiring grad with a method that does not differentiate with respect to it.
        TableauError: unknown method name; ``adaptive=True`` without an embedded pair.
        GraphMemoryError: a fixed-step explicit run with autograd whose graph would not fit
            in the available memory (the message names the remedies, e.g. ``checkpoint=True``).
    """
    x0 = check_state(x0)
    t = check_times(t, x0)
    chosen = resolve_method(method)
    if substeps is not None:
        check_int(substeps, "substeps")
    if max_steps is not None:
        check_int(max_steps, "max_steps")
    check_tolerances(
        DEFAULTS["rtol"] if rtol is None else rtol,
        DEFAULTS["atol"] if atol is None else atol,
        x0.dtype,
    )
    if compile is not None:
        compile = check_flag(compile, "compile", allow=("auto",))
    adaptive = check_flag(kwargs.pop("adaptive", None), "adaptive", allow=(None,))
    if stages is not None:
        check_int(stages, "stages")
    if dt0 is not None:
        _check_dt0(dt0)
    rhs = bind_rhs(f, u, t, interpolation=interpolation)
    if rhs.samples is not None:
        try:
            batch = torch.broadcast_shapes(rhs.samples.shape[:-2], x0.shape[:-1])
        except RuntimeError as exc:
            raise InputValidationError(
                f"the batch shape {tuple(rhs.samples.shape[:-2])} of the sampled input u does not "
                f"broadcast with the batch shape {tuple(x0.shape[:-1])} of x0."
            ) from exc
        x0 = x0.expand(*batch, x0.shape[-1])  # one initial state per input record
    x0 = _probe_rhs(rhs, x0, t, u is not None)
    options = dict(
        substeps=substeps,
        rtol=rtol,
        atol=atol,
        controller=controller,
        dt0=dt0,
        max_steps=max_steps,
        compile=compile,
        checkpoint=checkpoint,
    )
    if chosen.kind == AUTO:
        from .auto import choose_method
        from .implicit import check_solver_options

        if stages is not None:
            chosen.tableau(stages)  # raises: "auto" takes no stages
        chosen.check_options(AUTO, **options)
        check_solver_options(kwargs, adaptive=True)  # Radau's: refused now whatever is picked
        name, info = choose_method(rhs, x0, t)
        unused = sorted(kwargs) if name == "dopri5" else []
        kwargs = {} if unused else kwargs
        sol = _dispatch(rhs, x0, t, resolve_method(name), stages, adaptive, options, kwargs)
        sol.stats.extra["auto"] = {"method": name, **dict(info), "unused_options": unused}
        return sol
    return _dispatch(rhs, x0, t, chosen, stages, adaptive, options, kwargs)


def _dispatch(rhs, x0, t, method: Method, stages, adaptive, options, kwargs) -> Solution:
    """Run the solver of ``method`` (see the module docstring) after refusing the options
    that do not apply to it; ``options`` holds the values given (None: not given)."""
    tab = method.tableau(stages)
    kind = run_kind(tab, adaptive)
    method.check_options(kind, **{name: options[name] for name in OPTION_KINDS})
    opts = {
        name: DEFAULTS[name] if v is None and name in DEFAULTS else v for name, v in options.items()
    }
    if kind in (IMPLICIT_FIXED, IMPLICIT_ADAPTIVE):
        from .implicit import solve_implicit_ode

        if opts["dt0"] is not None:
            kwargs = {"dt0": opts["dt0"], **kwargs}
        return solve_implicit_ode(
            rhs,
            x0,
            t,
            tab,
            adaptive=kind == IMPLICIT_ADAPTIVE,
            rtol=opts["rtol"],
            atol=opts["atol"],
            substeps=opts["substeps"],
            max_steps=opts["max_steps"],
            controller=opts["controller"],
            **kwargs,
        )
    if kwargs:
        raise InputValidationError(
            f"unexpected keyword argument(s) {sorted(kwargs)} for the explicit method "
            f"{tab.name!r}; see the odeint docstring for the accepted options."
        )
    if kind == EXPLICIT_ADAPTIVE:
        from .adaptive import solve_adaptive

        return solve_adaptive(
            rhs,
            x0,
            t,
            tab,
            rtol=opts["rtol"],
            atol=opts["atol"],
            controller=opts["controller"],
            dt0=opts["dt0"],
            max_steps=opts["max_steps"],
        )
    return solve_explicit(
        rhs,
        x0,
        t,
        tab,
        substeps=opts["substeps"],
        compile=opts["compile"],
        checkpoint=opts["checkpoint"],
    )


def _check_dt0(dt0) -> None:
    """``dt0``: a positive finite number, or a tensor of them (per sample, adaptive explicit)."""
    if isinstance(dt0, torch.Tensor) and dt0.numel() > 1:
        values = dt0.detach()
        if not bool((torch.isfinite(values) & (values > 0)).all()):
            raise InputValidationError(f"dt0 must be finite and > 0 in every sample, got {dt0}.")
        return
    check_positive(dt0, "dt0", " (the first trial step of an adaptive method)")


def _probe_rhs(rhs, x0, t, with_input) -> torch.Tensor:
    """Evaluate f once at (t0, x0) to check its output; returns x0 (possibly expanded)."""
    signature = "f(t, x, u)" if with_input else "f(t, x)"
    try:
        with torch.no_grad():
            dx = rhs(t[0], x0)
    except TypeError as exc:
        raise InputValidationError(
            f"calling the model as {signature} failed: {exc}. The model is called with an "
            "input u only when odeint receives u."
        ) from exc
    except RuntimeError as exc:
        raise InputValidationError(
            f"calling the model as {signature} at t0 with x0 of shape {tuple(x0.shape)} "
            f"failed: {str(exc).splitlines()[0]}. A model with per-member (batched) "
            "parameters needs x0 of that batch: x0.expand(B, nx)."
        ) from exc
    if not isinstance(dx, torch.Tensor):
        raise InputValidationError(f"{signature} must return a tensor, got {type(dx).__name__}.")
    if dx.shape != x0.shape:
        try:
            grown = torch.broadcast_shapes(dx.shape, x0.shape) == dx.shape
        except RuntimeError:
            grown = False
        if not grown or dx.shape[-1] != x0.shape[-1]:
            raise InputValidationError(
                f"{signature} returned shape {tuple(dx.shape)} for x0 of shape "
                f"{tuple(x0.shape)}; it must return the state derivative, shape (*batch, nx)."
            )
        x0 = x0.expand(dx.shape).clone()
    if dx.dtype != x0.dtype:
        raise InputValidationError(
            f"{signature} returned dtype {dx.dtype} for x0 of dtype {x0.dtype}; create the "
            "model's tensors (parameters) in the state's dtype."
        )
    first = first_nonfinite(dx)
    if first is not None:
        raise InputValidationError(
            f"{signature} is non-finite at the initial time t = {float(t[0])} for sample "
            f"{first[:-1]}, state {first[-1]}; check the model and x0."
        )
    return x0
