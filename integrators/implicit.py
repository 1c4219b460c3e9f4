"""Implicit Runge-Kutta integration of stiff ODEs, implicit ODEs and index-1 DAEs (notes §7).

Public entry points:

- :func:`solve_implicit_ode`: ``x' = rhs(t, x)`` with a Gauss-Legendre, Radau IIA
  or any implicit tableau, fixed step (eq. 7.14-7.18) or adaptive (Radau IIA, odd ``s``).
- :func:`daeint`: :class:`~integrators.problems.ImplicitODE` (eq. 7.51-7.52),
  :class:`~integrators.problems.SemiExplicitDAE` (eq. 7.63) and
  :class:`~integrators.problems.ImplicitDAE` (eq. 7.56-7.60), after an index check
  (Theorem 9, Corollary 1) and a consistent initialisation of the algebraic states.

Stage equations are solved by simplified Newton with the factorisation reused across
iterations and steps; for tableaus with invertible, diagonalisable ``A`` (Radau IIA, Gauss) the
``s p x s p`` Newton system is split into one real / complex ``p x p`` solve per eigenvalue
(pair) of ``A^{-1}``, and small systems (``s p <= 24``) are inverted once per factorisation so
that a Newton iteration is one batched matrix-vector product. When the model takes no input and
accepts an extra leading batch dimension (checked once per call against stage-by-stage
evaluation), all ``s`` stages are evaluated in one call (``stats.extra["stacked_stages"]``).
Per-sample step control and Newton bookkeeping run on the host (numpy), one device-to-host
transfer per Newton iteration and step. Reverse-mode gradients use the implicit function
theorem at every step (one transposed linear solve per step; memory independent of the
number of Newton iterations): they reach ``x0`` and every tensor requiring grad that the
model uses (``nn.Module`` parameters or captured tensors). Step sizes and times are not
differentiated.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ._irk_core import EPS, InputSignal, IRKCore
from ._irk_fixed import integrate_fixed
from ._irk_system import StageSystem, rank_ratio
from ._options import (
    LINEAR_SOLVERS,
    broadcast_tolerance,
    check_flag,
    check_int,
    check_positive,
    check_state,
    check_times,
    check_tolerances,
    raise_shape_change,
    refuse_time_gradient,
    sample_indices,
)
from .controllers import GustafssonController, check_controller
from .errors import ConvergenceError, HighIndexError, InputValidationError, TableauError
from .methods import IMPLICIT_ADAPTIVE, resolve_method, run_kind
from .problems import ImplicitDAE, ImplicitODE, SemiExplicitDAE
from .solution import Solution, SolverStats
from .tableau import ButcherTableau

__all__ = ["daeint", "solve_implicit_ode"]

_NEWTON_KEYS = {
    "max_iter",
    "newton_tol",
    "linear_solver",
    "dt0",
    "index_tol",
    "index_check_every",
    "host_loop",
}


def _implicit_tableau(method, stages, adaptive) -> tuple[ButcherTableau, bool]:
    """The implicit tableau that ``method`` (a name or a tableau, :func:`resolve_method`) and
    ``stages`` give, and whether its run controls the step size (``adaptive``: True, False or
    None for the method's default)."""
    tab = resolve_method(method).tableau(stages)
    if tab.is_explicit:
        raise TableauError(
            f"tableau {tab.name!r} is explicit; use odeint for explicit methods, or pass an "
            "implicit tableau here."
        )
    kind = run_kind(tab, check_flag(adaptive, "adaptive", allow=(None,)))
    return tab, kind == IMPLICIT_ADAPTIVE


def check_solver_options(options: dict, adaptive: bool) -> dict:
    """Check the solver options (``**newton_options``) of an integration with or without
    step-size control (``adaptive``) and return them."""
    unknown = set(options) - _NEWTON_KEYS
    if unknown:
        raise InputValidationError(
            f"unknown option(s) {sorted(unknown)} for the implicit solver; known options are "
            f"{sorted(_NEWTON_KEYS)}."
        )
    for name in ("max_iter", "index_check_every"):
        if name in options:
            check_int(options[name], name)
    for name in ("newton_tol", "index_tol"):
        if options.get(name) is not None:
            check_positive(options[name], name)
    solver = options.get("linear_solver", "auto")
    if not (isinstance(solver, str) and solver in LINEAR_SOLVERS):
        raise InputValidationError(
            f"unknown linear_solver {solver!r}; use one of {', '.join(map(repr, LINEAR_SOLVERS))}."
        )
    options = dict(
        options,
        host_loop=check_flag(options.get("host_loop", "auto"), "host_loop", allow=("auto",)),
    )
    if options.get("dt0") is not None:
        if not adaptive:
            raise InputValidationError(
                "dt0 sets the first step of adaptive Radau IIA; this integration runs at fixed "
                "steps (set their number per output interval with substeps)."
            )
        check_positive(options["dt0"], "dt0", " (the first trial step; one number for the batch)")
    return options


@dataclass(frozen=True)
class _Settings:
    """The checked options of one implicit integration (:func:`_entry`)."""

    tab: ButcherTableau
    adaptive: bool
    rtol: object
    atol: object
    substeps: int
    max_steps: int
    controller: object
    options: dict


def _entry(x0, t, method, stages, adaptive, controller, newton_options, run, algebraic=False):
    """The entry checks shared by :func:`solve_implicit_ode` and :func:`daeint`: the state
    (:func:`check_state`), the method, the controller, the solver options, ``run`` (``rtol``,
    ``atol``, ``substeps``, ``max_steps``) and the output times; returns ``(x0, t, settings)``.
    ``algebraic``: the problem has algebraic states (its x0 may then be empty)."""
    x0 = check_state(x0, "x0", min_width=0 if algebraic else 1)
    tab, adaptive = _implicit_tableau(method, stages, adaptive)
    check_controller(controller, tab.name, adaptive)
    options = check_solver_options(newton_options, adaptive)
    check_tolerances(run["rtol"], run["atol"], x0.dtype)
    # tensor tolerances: per state (*batch, nx), or per sample (*batch, 1) beside algebraic states
    shape = (*x0.shape[:-1], 1) if algebraic else x0.shape
    hint = (
        ": a problem with algebraic states takes one tolerance per sample."
        if algebraic
        else ", the states' shape."
    )
    run = dict(
        run,
        rtol=broadcast_tolerance(run["rtol"], "rtol", shape, x0, hint),
        atol=broadcast_tolerance(run["atol"], "atol", shape, x0, hint),
        substeps=check_int(run["substeps"], "substeps"),
        max_steps=check_int(run["max_steps"], "max_steps"),
    )
    refuse_time_gradient(t, tab.name)
    t = check_times(t, x0).detach()
    return x0, t, _Settings(tab, adaptive, controller=controller, options=options, **run)


def _empty_solution(x0, z0, t, method_name, with_z) -> Solution:
    """The result of an integration of an empty batch (a zero batch dimension)."""
    batch, T = x0.shape[:-1], t.shape[0]
    x = x0.new_empty(*batch, T, x0.shape[-1])
    z = z0.new_empty(*batch, T, z0.shape[-1])
    return Solution(
        t=t.detach(),
        x=x,
        z=z if with_z else None,
        status=torch.zeros(batch, dtype=torch.int8, device=x0.device),
        stats=SolverStats(),
        method=method_name,
        interpolant=lambda tq: x0.new_empty(*batch, tq.shape[0], x0.shape[-1]),
    )


def newton_tolerance(rtol, dtype, override=None) -> float:
    """Stage-solve tolerance on ``eta ||dW||`` (Hairer-Wanner's rule, scaled norm) for the
    smallest entry of ``rtol`` (a number or a tensor)."""
    if override is not None:
        return float(override)
    rtol = float(torch.as_tensor(rtol).min())
    eps = EPS.get(dtype, EPS[torch.float32])
    return max(10.0 * eps / rtol, min(0.03, rtol**0.5))


def _run(core, settings: _Settings, x0, z0, xdot0, t, extra: dict, messages: list):
    """Integrate from the consistent start ``(x0, z0, xdot0)`` with the adaptive loop and the
    kernel :func:`integrators._radau_host.use_host_loop` picks, or at fixed steps."""
    adaptive, rtol, atol = settings.adaptive, settings.rtol, settings.atol
    options, controller = settings.options, settings.controller
    max_iter = int(options.get("max_iter", 7 if adaptive else 15))
    tol = newton_tolerance(rtol, x0.dtype, options.get("newton_tol"))
    index_tol = float(options.get("index_tol", 1e-10))
    every = int(options.get("index_check_every", 10))
    from ._radau_host import NumpyKernel, OneTrajectoryKernel, one_trajectory, use_host_loop
    from .radau import TorchKernel, adaptive_loop

    host_option = options.get("host_loop", "auto")
    if controller is not None and not isinstance(controller, GustafssonController):
        # the numpy kernels step with Gustafsson's rule only; a user's I/PI controller drives
        # the steps with the torch kernel
        if host_option is True:
            raise InputValidationError(
                f"host_loop=True runs Radau IIA's own GustafssonController; the controller "
                f"{controller!r} needs the torch driver: pass host_loop=False or 'auto'."
            )
        host_option = False
    host_loop = use_host_loop(core, x0, host_option, adaptive)
    single = host_loop and one_trajectory(x0)
    if adaptive:
        if host_loop:
            kernel_class = OneTrajectoryKernel if single else NumpyKernel
            kernel = kernel_class(core, x0, z0, xdot0, t, rtol, atol, tol, max_iter)
        else:
            kernel = TorchKernel(core, x0, z0, xdot0, t, rtol, atol, tol, max_iter, index_tol)
        out = adaptive_loop(
            kernel,
            core,
            x0,
            z0,
            xdot0,
            t,
            rtol=rtol,
            atol=atol,
            max_steps=settings.max_steps,
            max_iter=max_iter,
            index_check_every=every,
            dt0=options.get("dt0"),
            controller=controller,
        )
    else:
        out = integrate_fixed(
            core,
            x0,
            z0,
            xdot0,
            t,
            substeps=settings.substeps,
            rtol=rtol,
            atol=atol,
            max_iter=max_iter,
            newton_tol=tol,
            index_tol=index_tol,
            index_check_every=every,
        )
    records = out["records"]
    stats = SolverStats(
        n_f_evals=out["n_f"],
        n_steps=out["n_steps"],
        n_rejected=out.get("n_rejected", 0),
        n_newton_iters=out["n_newton"],
        n_factorizations=out["n_lu"],
        n_jac_evals=out["n_jac"],
        extra=dict(
            extra,
            linear_solver=core.solver.mode,
            tableau=core.tab.name,
            stacked_stages=bool(core.stack_stages),
            host_loop=host_loop,
            driver="host, one trajectory" if single else "host" if host_loop else "torch",
            **({"controller": repr(controller or GustafssonController())} if adaptive else {}),
        ),
    )
    return Solution(
        t=t,
        x=out["x"],
        status=out["status"],
        stats=stats,
        z=out["z"] if core.system.m else None,
        messages=messages + out["messages"],
        method=settings.tab.name,
        interpolant=None if records is None else (lambda tq: records.evaluate(tq)[0]),
    )


def solve_implicit_ode(
    rhs,
    x0,
    t,
    method="radau_iia",
    *,
    stages=None,
    adaptive=None,
    rtol=1e-6,
    atol=1e-9,
    substeps=1,
    max_steps=100_000,
    controller=None,
    **newton_options,
) -> Solution:
    """Integrate the explicit ODE ``x' = rhs(t, x)`` with an implicit RK method.

    Args:
        rhs: ``rhs(t, x) -> (*batch, n)``, e.g. a ``BoundRHS`` from ``bind_rhs`` (its input is
            then held per step as in eq. 8.34 in fixed-step mode).
        x0: (*batch, n) initial states.
        t: (T,) strictly increasing output times.
        method: "radau_iia", "gauss_legendre", "implicit_euler", "implicit_midpoint" or an
            implicit :class:`ButcherTableau`.
        stages: number of collocation stages (default 3 for Radau IIA, 2 for Gauss-Legendre).
        adaptive: error-controlled steps (Radau IIA with odd ``s`` only); default True for
            Radau IIA, False otherwise.
        rtol, atol: local error tolerances (adaptive) and the Newton stopping scale
            ``atol + rtol |x|`` (both modes): numbers or tensors broadcasting to the states
            (*batch, n) (per component and sample).
        substeps: fixed-step mode: steps per output interval.
        max_steps: adaptive mode: step attempts per sample before MAX_STEPS.
        controller: adaptive mode: the step-size controller (:mod:`integrators.controllers`);
            None or a :class:`~integrators.controllers.GustafssonController` runs Radau IIA's
            predictive rule in any driver, an I or PI controller runs the torch driver
            (``stats.extra["driver"]``, ``stats.extra["controller"]``).
        **newton_options: ``max_iter`` (Newton iterations per stage solve, 7 adaptive / 15
            fixed), ``newton_tol`` (override of the stopping tolerance), ``linear_solver``
            ("auto", "transformed", "full"), ``dt0`` (first step, adaptive), ``host_loop``
            (adaptive explicit ODEs on the CPU: "auto" (default) runs the step loop in numpy
            when ``s n <= 24`` and ``x0.numel() <= 1024``, where it takes the same steps
            faster than the vectorised torch loop, and a single float64 trajectory runs it
            with the step control in Python floats, faster again (docs/benchmarks.md); True forces
            it (an error where impossible), False keeps the torch loop; the choice is in
            ``stats.extra["host_loop"]`` and ``stats.extra["driver"]`` ("torch", "host" or
            "host, one trajectory")); for DAEs
            ``index_tol`` and ``index_check_every`` (steps between forced Jacobian
            re-evaluations for the rank test, default 10).

    Returns:
        :class:`Solution` with per-sample ``status`` and ``stats`` (Newton iterations,
        factorisations, Jacobian evaluations, steps, rejections) and dense output ``at``;
        an empty batch (a zero batch dimension) gives an empty Solution.

    Raises:
        InputValidationError: at entry, for any option outside its domain (non-bool
            ``adaptive`` / ``host_loop``, non-integer or < 1 ``substeps`` / ``max_steps`` /
            ``max_iter`` / ``index_check_every``, ``newton_tol`` / ``index_tol`` / ``dt0``
            not finite and > 0, ``dt0`` without step-size control, an unknown
            ``linear_solver``, tolerances failing
            :func:`integrators._options.check_tolerances`), ``stages`` with a method other
            than "gauss_legendre" / "radau_iia", a ``controller`` that is not one or is given
            to a fixed-step run, a state dtype other than float32/float64, or
            ``t`` requiring grad (output times are not differentiated); during the run, a
            model output whose shape differs from the state's.
    """
    run = dict(rtol=rtol, atol=atol, substeps=substeps, max_steps=max_steps)
    x0, t, settings = _entry(x0, t, method, stages, adaptive, controller, newton_options, run)
    tab, adaptive, options = settings.tab, settings.adaptive, settings.options
    kind = getattr(rhs, "kind", None)
    if kind is not None and hasattr(rhs, "f"):
        fn, has_input, signal = rhs.f, kind != "none", InputSignal(rhs)
    else:
        fn, has_input, signal = rhs, False, InputSignal(None)
    system = StageSystem("ode", x0.shape[-1], 0, (_shape_checked(fn),), has_input)
    core = IRKCore(tab, system, signal, x0.dtype, x0.device, options.get("linear_solver", "auto"))
    z0 = x0.new_zeros(*x0.shape[:-1], 0)
    t0 = t[0].expand(*x0.shape[:-1], 1) if adaptive else t[0]
    with torch.no_grad():
        xdot0 = fn(t0, x0, signal.at(t0)) if has_input else fn(t0, x0)
    _check_derivative_shape(xdot0, x0)
    if x0.shape[:-1].numel() == 0:
        return _empty_solution(x0, z0, t, tab.name, with_z=False)
    return _run(core, settings, x0, z0, xdot0, t, extra={}, messages=[])


def _shape_checked(fn):
    """``fn(t, x[, u])`` that raises when its output does not have the shape of the state
    ``x`` it is given: broadcasting would otherwise hide a model whose output changes shape
    during the integration (one tuple comparison per call)."""

    def checked(t, x, *u):
        out = fn(t, x, *u)
        if getattr(out, "shape", None) != x.shape:
            raise_shape_change(out, x, t)
        return out

    return checked


def _check_derivative_shape(xdot0, x0) -> None:
    """The model's output at (t0, x0) must be a tensor of the state's shape."""
    if not isinstance(xdot0, torch.Tensor):
        raise InputValidationError(f"rhs must return a tensor, got {type(xdot0).__name__}.")
    if xdot0.shape != x0.shape:
        raise InputValidationError(
            f"rhs(t0, x0) returned shape {tuple(xdot0.shape)} for x0 of shape "
            f"{tuple(x0.shape)}; it must return the state derivative, shape (*batch, n) "
            "(odeint expands x0 when the model's parameters carry a larger batch)."
        )


def daeint(
    problem,
    x0,
    z0,
    t,
    *,
    method="radau_iia",
    stages=None,
    adaptive=None,
    rtol=1e-6,
    atol=1e-9,
    u=None,
    interpolation="zoh",
    substeps=1,
    max_steps=100_000,
    controller=None,
    **newton_options,
) -> Solution:
    """Integrate an implicit ODE or an index-1 DAE with an implicit RK method.

    Before the first step the index is checked (``dg/dz`` for :class:`SemiExplicitDAE`,
    ``[dF/dx', dF/dz]`` for :class:`ImplicitDAE`, ``dF/dx'`` for :class:`ImplicitODE` must have
    full rank; Theorem 9, Corollary 1, eq. 5.53, 5.56) and the initial algebraic states (and
    the initial derivative of implicit problems) are made consistent by a Newton solve; the
    correction is reported in ``sol.stats.extra["z0_correction"]`` ((*batch,) max-norm) and in
    ``sol.messages``. The rank test is repeated whenever the Jacobian is re-evaluated.

    Args:
        problem: :class:`ImplicitODE`, :class:`SemiExplicitDAE` or :class:`ImplicitDAE`.
        x0: (*batch, n) initial differential states.
        z0: (*batch, m) guess of the initial algebraic states (None for ImplicitODE); only a
            starting point of the consistency Newton solve, so it receives no gradient (the
            consistent ``z(t0)`` carries the derivatives of that root with respect to ``x0``
            and every tensor the model uses, first and second order).
        t: (T,) strictly increasing output times.
        method, stages, adaptive, rtol, atol, substeps, max_steps, controller: as in
            :func:`solve_implicit_ode` (tensor tolerances of a problem with algebraic states
            give one value per sample, (*batch, 1)).
        **newton_options: as in :func:`solve_implicit_ode`; ``index_tol`` (default 1e-10) is
            the relative singular-value threshold of the rank test.
        u: input: None, a callable ``u(t)`` or samples (T, nu) / (*batch, T, nu) on ``t``.
        interpolation: "zoh" or "linear" for sampled inputs (see :mod:`integrators.inputs`).

    Returns:
        :class:`Solution` with ``x`` (*batch, T, n) and ``z`` (*batch, T, m) (None for
        ImplicitODE). With a zero-order-hold input ``z`` at an output time ``t_j`` is the
        end of the interval ending there: it solves ``g(x_j, z_j, u_{j-1}) = 0`` (the hold
        of ``[t_{j-1}, t_j]``, closed), every method alike; ``z`` at ``t_0`` uses ``u_0``.

    Raises:
        InputValidationError: options as in :func:`solve_implicit_ode`.
        HighIndexError: the index-check matrix is rank deficient at the initial point.
        ConvergenceError: no consistent initial algebraic state was found.
    """
    if not isinstance(problem, ImplicitODE | SemiExplicitDAE | ImplicitDAE):
        raise InputValidationError(
            f"daeint expects an ImplicitODE, SemiExplicitDAE or ImplicitDAE, got "
            f"{type(problem).__name__}; for x' = f(t, x) use odeint."
        )
    run = dict(rtol=rtol, atol=atol, substeps=substeps, max_steps=max_steps)
    algebraic = not isinstance(problem, ImplicitODE)
    x0, t, settings = _entry(
        x0, t, method, stages, adaptive, controller, newton_options, run, algebraic
    )
    tab, adaptive, options = settings.tab, settings.adaptive, settings.options
    if not algebraic:
        if z0 is not None and torch.as_tensor(z0).numel():
            raise InputValidationError("an ImplicitODE has no algebraic states: pass z0=None.")
        z0 = x0.new_zeros(*x0.shape[:-1], 0)
    else:
        if z0 is None:
            raise InputValidationError(
                f"{type(problem).__name__} needs a guess z0 of shape (*batch, m) of the "
                "initial algebraic states (it is made consistent before the first step)."
            )
        z0 = check_state(z0, "z0", dtype=x0.dtype, device=x0.device, min_width=0)
        if z0.shape[:-1] != x0.shape[:-1]:
            try:
                fits = torch.broadcast_shapes(z0.shape[:-1], x0.shape[:-1]) == x0.shape[:-1]
            except RuntimeError:
                fits = False
            if not fits:
                raise InputValidationError(
                    f"z0 has batch shape {tuple(z0.shape[:-1])} but x0 has "
                    f"{tuple(x0.shape[:-1])}: give z0 the shape (*batch, m) of x0's batch (or "
                    "a shape that broadcasts to it, e.g. (m,) for one guess shared by all)."
                )
            z0 = z0.expand(*x0.shape[:-1], z0.shape[-1])
    if adaptive and x0.shape[-1] == 0:
        raise InputValidationError(
            "x0 has width 0 (a purely algebraic problem): the adaptive step control measures "
            "the error of the differential states, so there is nothing to control; pass "
            "adaptive=False (z is then solved from g = 0 at every step)."
        )
    if x0.shape[:-1].numel() == 0:
        return _empty_solution(x0, z0, t, tab.name, with_z=algebraic)
    from .inputs import bind_rhs

    signal = InputSignal(
        None if u is None else bind_rhs(lambda tt, xx, uu: uu, u, t, interpolation=interpolation)
    )
    system = StageSystem(
        problem.kind, x0.shape[-1], z0.shape[-1], problem.functions(), u is not None
    )
    core = IRKCore(tab, system, signal, x0.dtype, x0.device, options.get("linear_solver", "auto"))
    t0 = t[0].expand(*x0.shape[:-1], 1) if adaptive else t[0]
    problem.check_start(t0, x0, z0, signal.at(t0) if u is not None else None)
    index_tol = float(options.get("index_tol", 1e-10))
    z0c, xdot0, correction, msgs = consistent_start(system, signal, t0, x0, z0, index_tol)
    extra = {"z0_correction": correction} if system.m else {}
    return _run(core, settings, x0, z0c, xdot0, t, extra, msgs)


def consistent_start(system: StageSystem, signal: InputSignal, t0, x0, z0, index_tol):
    """Index check and consistent ``(z0, x'(t0))`` by Newton (notes §5.4, eq. 5.53-5.58).

    Returns:
        ``(z0, xdot0, correction, messages)`` with ``correction`` the (*batch,) max-norm of
        the change made to ``z0``.
    """
    m = system.m
    u0 = signal.at(t0)
    _check_index(system, t0, torch.zeros_like(x0.detach()), x0, z0.detach(), u0, index_tol)
    xdot0, z_new, res = system.algebraic_states(t0, x0, z0, u0)
    if not bool(res.converged.all()):
        idx, _ = sample_indices(~res.converged, 10)
        what = "g(t0, x0, z) = 0 for z" if system.kind == "semi" else "F(t0, x0', x0, z) = 0"
        raise ConvergenceError(
            f"consistent initialisation failed: Newton on {what} did not converge for samples "
            f"{idx}. Give a better z0 guess, or check that the DAE has a solution at t0."
        )
    _check_index(system, t0, xdot0, x0, z_new, u0, index_tol)
    correction = (z_new - z0).detach().abs().amax(-1) if m else x0.new_zeros(x0.shape[:-1])
    msgs = []
    if m and bool((correction > 0).any()):
        changed, n_changed = sample_indices(correction > 0, 10)
        worst = tuple(torch.nonzero(correction == correction.max())[0].tolist())
        msgs.append(
            f"initial algebraic states z0 were inconsistent (g != 0) for {n_changed} "
            f"sample(s) {changed}; corrected by Newton, largest "
            f"change {float(correction.max()):.3g} (max-norm) at sample {worst} (see "
            "stats.extra['z0_correction'])."
        )
    return z_new, xdot0.detach(), correction, msgs


def _check_index(system, t0, xdot, x, z, u, index_tol):
    """Raise HighIndexError where the index-check matrix is rank deficient (Theorem 9)."""
    with torch.no_grad():
        _, _, index_matrix, reference = system.blocks(t0, xdot.detach(), x.detach(), z.detach(), u)
        ratio = rank_ratio(index_matrix, reference)
    bad = ratio <= index_tol
    if not bool(bad.any()):
        return
    idx, _ = sample_indices(bad, 10)
    which = "dg/dz" if system.kind == "semi" else ("[dF/dx', dF/dz]" if system.m else "dF/dx'")
    found = (
        f"{which} is rank deficient at t0 for samples {idx} (smallest singular value / "
        f"Jacobian norm = {float(ratio[bad].min()):.2e} <= index_tol = {index_tol:g}; "
        "Theorem 9, Corollary 1)"
    )
    reduce = (
        "Implicit RK methods give meaningless results on DAEs of index > 1 (notes §7.6.1): "
        "index-reduce the model (differentiate the constraints, notes §5.4-5.5) before "
        "calling daeint."
    )
    if system.kind != "semi" and not system.m:
        raise HighIndexError(
            f"F(t, x', x) = 0 is not an implicit ODE: {found}, so it is a DAE. If the "
            "singular part of dF/dx' belongs to states whose derivatives do not enter F "
            "(algebraic states), write the model as ImplicitDAE F(t, x', x, z) with those "
            "states in z (and x0, z0 split accordingly): daeint integrates it when "
            "[dF/dx', dF/dz] is invertible (index 1). If the derivatives enter only in a "
            "singular combination, combine the equations or change variables so that the "
            "algebraic states appear without derivatives (notes §5.1) first. "
            f"{reduce}"
        )
    raise HighIndexError(f"the DAE is of index > 1: {found}. {reduce}")
