"""Fitting grey-box continuous-time models through the Runge-Kutta layers.

Criteria (``criterion=`` of :func:`sysid.fit`), all least squares or robust M-estimation of
output errors ``e_k = y_k - yhat_k`` sampled at the data's times:

* ``"simulation"``: the free-run simulation error of the whole record from the initial state
  (output error, the course notes (Modelling and Simulation) eq. 4.133 for a continuous-time
  model). The statistically efficient criterion under white output noise; the covariance
  ``sigma^2 (J'J)^{-1}`` (eq. 4.101 form) refers to it. Needs a start inside the basin of
  attraction: on oscillatory plants a poor start converges to a wrong local minimum.
* ``"multiple_shooting"``: the record cut into segments of ``segment_length`` intervals, each
  simulated from its own free initial state (node), the continuity of the trajectory
  ``x_end,j = s_{j+1}`` enforced by quadratic penalties of increasing weight (a penalty
  continuation). Only the outputs need to be measured: unmeasured node states are estimated.
  Short segments keep the simulation error nearly linear in the parameters, which widens the
  basin of attraction; the estimate is then polished by the simulation criterion from the
  fitted parameters and first node, so its covariance is that of the simulation error.
* ``"one_step"``: where every state is measured (the output selects all states), the error
  of one step of the integrator from each measured state: an equation-error fit, fast and
  with no simulation over the record, biased under measurement noise; use it for starting
  values.

The Jacobian of the residuals comes from the exact forward sensitivities of the discrete
simulation (eq. 8.17-8.18 explicit, 8.24-8.28 implicit; parameters and initial states only, no
input sensitivities), chained through the bounded-parameter transforms; the minimiser is the
batched Levenberg-Marquardt iteration of :mod:`sysid.estimation` (eq. 3.61 damping). Every data
set of a batch is fitted independently in the same call.
"""

from __future__ import annotations

import importlib
import math
import time
import warnings

import numpy as np
import torch

from integrators.block_jacobian import BlockJacobian
from integrators.errors import InputValidationError
from integrators.newton import NewtonStatus, minimize

from .._progress import progress_bar
from ..data import IOData
from ..errors import ConvergenceWarning, ParameterAtBoundWarning, PoorExcitationWarning
from ..estimation.losses import LOSSES, GaussianLoss, make_loss
from ..estimation.results import STATIONARY_TOL, FitResult, covariance, remaining_step
from .greybox import GreyBoxModel, Segments, initial_states

#: the module (``integrators.sensitivities`` names its function too): its threshold is read
#: at call time
_compile_policy = importlib.import_module("integrators._fast.compiled")

__all__ = ["CRITERIA", "fit_greybox", "simulation_quality"]

CRITERIA = ("simulation", "multiple_shooting", "one_step")

#: continuity penalty weights of multiple shooting, applied in turn (each run starts from the
#: previous estimate); relative to the output scale, see ``_Problem.defect_weight``
_PENALTY_CONTINUATION = (1.0, 1e2, 1e4)

#: default multiple-shooting segments: this many sample intervals, longer where the record
#: would otherwise have more than ``_MAX_SEGMENTS`` segments (the covariance of a fit
#: interrupted during multiple shooting is formed from the dense Jacobian over all nodes)
_SEGMENT_SAMPLES = 10
_MAX_SEGMENTS = 100

#: a Levenberg-Marquardt run evaluates its residuals at least this many times (iterations
#: and line-search trials): where the first, eager simulation of a fit took at least
#: ``1 / (runs _FIT_EVALUATIONS)`` of
#: :data:`integrators._fast.compiled.AUTO_COMPILE_EAGER_SECONDS` (``runs``: the
#: Levenberg-Marquardt runs still to come, e.g. one per penalty stage of multiple shooting),
#: the fit would reach that rent-or-buy threshold anyway and compiles (``compile="auto"``)
#: at once
_FIT_EVALUATIONS = 20

#: |correlation| of two estimates above which the pair is reported as not separately
#: identifiable from the data
_IDENTIFIABILITY_CORRELATION = 0.999
#: an estimate closer to a bound than this fraction of its start's distance is at the bound
_AT_BOUND = 1e-6


class _Problem:
    """Residuals and Jacobian of one criterion for a batch of data sets, in the unconstrained
    coordinates ``z`` of the free quantities (layout: shared free parameters, then per
    experiment its per-experiment free parameters, its initial state if estimated and its
    multiple-shooting nodes)."""

    def __init__(self, model: GreyBoxModel, data: IOData, criterion, x0, segment_length, method):
        self.model, self.data, self.criterion, self.method = model, data, criterion, method
        self.x0 = x0  # the fit's x0 option: None (the model's), "zero", "estimate" or tensors
        self.ny = data.ny
        self.batch = data.batch_shape
        self.dtype, self.device = data.dtype, data.device
        nx = model.nx
        self.parts = data.experiment_list
        E = len(self.parts)
        self.column_names: list[str] = []
        self.reported: list[int] = []  # columns reported in the result (params and x0)
        self.param_columns: list[list[int | None]] = []  # per experiment, per param
        self.starts_z: list[torch.Tensor] = []
        self.scales: dict[tuple[str, int], torch.Tensor] = {}
        self.fixed: dict[tuple[str, int], torch.Tensor] = {}
        col = 0
        shared = {}
        for n in model.names:
            p = model.params[n]
            if p.free and not p.per_experiment:
                start = self._start(n, E, 0)
                shared[n] = col
                self.scales[(n, 0)] = p.scale(start)
                self.starts_z.append(p.to_unconstrained(start, self.scales[(n, 0)])[..., None])
                self.column_names.append(n)
                self.reported.append(col)
                col += 1
        self.x0_columns: list[list[int] | None] = []
        self.node_columns: list[list[int] | None] = []
        self.segments: list[Segments] = []
        self.known_x0: list[torch.Tensor | None] = []
        given_x0 = initial_states(model.x0 if x0 is None else x0, nx, E)
        self.nodes_measured: list[torch.Tensor | None] = []
        idx_out = model.output_indices(self.ny)
        self.idx_out = idx_out
        if criterion == "one_step" and (idx_out is None or sorted(idx_out) != list(range(nx))):
            raise InputValidationError(
                "criterion='one_step' needs every state measured: the output must select all "
                f"nx = {nx} states (output={model.output!r}); use 'simulation' or "
                "'multiple_shooting' when only outputs are measured."
            )
        for e, part in enumerate(self.parts):
            cols = []
            for n in model.names:
                p = model.params[n]
                if not p.free:
                    self.fixed[(n, e)] = self._start(n, E, e)
                    cols.append(None)
                elif not p.per_experiment:
                    cols.append(shared[n])
                else:
                    start = self._start(n, E, e)
                    self.scales[(n, e)] = p.scale(start)
                    self.starts_z.append(p.to_unconstrained(start, self.scales[(n, e)])[..., None])
                    self.column_names.append(f"{n}[{e}]" if E > 1 else n)
                    self.reported.append(col)
                    cols.append(col)
                    col += 1
            self.param_columns.append(cols)
            N = part.N
            if N < 2:
                raise InputValidationError(f"experiment {e} has N = {N} < 2 samples.")
            if criterion == "simulation":
                seg = Segments(torch.zeros(1, dtype=torch.int64), N - 1)
            elif criterion == "one_step":
                seg = Segments(torch.arange(N - 1, dtype=torch.int64), 1)
            else:
                L = segment_length
                if L is None:
                    L = max(_SEGMENT_SAMPLES, math.ceil((N - 1) / _MAX_SEGMENTS))
                if isinstance(L, bool) or int(L) != L or L < 1:
                    raise InputValidationError(
                        f"segment_length must be an integer >= 1, got {segment_length!r}."
                    )
                L = min(int(L), N - 1)
                S = math.ceil((N - 1) / L)
                seg = Segments(torch.arange(S, dtype=torch.int64) * L, L)
            self.segments.append(seg)
            # initial state of the experiment
            if criterion == "one_step":
                self.x0_columns.append(None)
                self.known_x0.append(None)
            elif isinstance(x0, str) and x0 == "estimate":
                self.x0_columns.append(list(range(col, col + nx)))
                suffix = f"[{e}]" if E > 1 else ""
                names = model.state_names or tuple(str(i) for i in range(nx))
                self.column_names += [f"x0{suffix}.{s}" for s in names]
                self.reported += list(range(col, col + nx))
                self.starts_z.append(
                    self._node_guess(part, torch.zeros(1, dtype=torch.int64))[..., 0, :]
                )
                col += nx
                self.known_x0.append(None)
            else:
                self.x0_columns.append(None)
                self.known_x0.append(self._known_x0(given_x0[e]))
            # further nodes of multiple shooting
            if criterion == "multiple_shooting" and seg.starts.shape[0] > 1:
                S = seg.starts.shape[0]
                self.node_columns.append(list(range(col, col + (S - 1) * nx)))
                self.column_names += [f"node{j}.{i}" for j in range(1, S) for i in range(nx)]
                self.starts_z.append(self._node_guess(part, seg.starts[1:]).flatten(-2))
                col += (S - 1) * nx
            else:
                self.node_columns.append(None)
            self.nodes_measured.append(
                part.y[..., seg.starts, :][..., torch.argsort(torch.tensor(idx_out))]
                if criterion == "one_step"
                else None
            )
        self.n_columns = col
        #: (*batch, nx) weights of the continuity defects (multiple shooting), set per
        #: penalty stage by :func:`_multiple_shooting`
        self.defect_weight = torch.ones(model.nx, dtype=self.dtype, device=self.device)
        #: the ``compile`` of the simulations (None: the model's), see :func:`_check_start`
        self.compile = None

    # ----------------------------------------------------------------------- start values
    def _known_x0(self, value) -> torch.Tensor:
        """A known initial state (checked by :func:`initial_states`) in the data's dtype;
        None or "zero": zeros. Its batch must broadcast to the data's batch without widening
        it (the fit is batched over data sets, not over initial states)."""
        nx = self.model.nx
        if value is None or isinstance(value, str):
            return torch.zeros(nx, dtype=self.dtype, device=self.device)
        if not _within_batch(value.shape[:-1], self.batch):
            raise InputValidationError(
                f"fit: the known initial state x0 {tuple(value.shape)} does not match the data's "
                f"batch {tuple(self.batch)}; x0 must be ({nx},) or (*data batch, {nx}) = "
                f"{tuple(self.batch) + (nx,)}. To fit one data set per initial state, give "
                "data batched like x0."
            )
        return value.to(device=self.device, dtype=self.dtype)

    def _node_guess(self, part: IOData, at: torch.Tensor) -> torch.Tensor:
        """Start values of node states at samples ``at``: the measured states where the
        output selects them, zero for the others: (*batch, len(at), nx) or (nx,)-like."""
        nx = self.model.nx
        guess = torch.zeros(
            *part.batch_shape, at.shape[0], nx, dtype=self.dtype, device=self.device
        )
        if self.idx_out is not None:
            guess[..., self.idx_out] = part.y[..., at, :]
        return guess

    def _start(self, name: str, n_experiments: int, experiment: int) -> torch.Tensor:
        """Parameter ``name``'s (starting) value in ``experiment``: () or, from a fitted
        model, one per data set (its batch must broadcast to the data's)."""
        start = self.model.params[name].start(n_experiments, experiment)
        if not _within_batch(start.shape, self.batch):
            raise InputValidationError(
                f"fit: parameter {name!r} has values of batch {tuple(start.shape)} (a model "
                f"fitted to that many data sets) for data of batch {tuple(self.batch)}; fit "
                "data of the model's batch, or give the parameter one value (Param)."
            )
        return start

    def initial_z(self) -> torch.Tensor:
        """(*batch, n_columns) start of the minimiser."""
        pieces = [z.to(self.dtype).expand(*self.batch, z.shape[-1]) for z in self.starts_z]
        return torch.cat(pieces, -1).clone()

    # ----------------------------------------------------------------------- evaluation
    def physical(self, z: torch.Tensor, e: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The parameter values of experiment ``e``, ``P`` (*batch, n_params), and their
        derivatives ``dP/dz`` (*batch, n_params, n_columns) (zero rows for fixed ones)."""
        names = self.model.names
        values = []
        D = z.new_zeros(*z.shape[:-1], len(names), self.n_columns)
        for j, n in enumerate(names):  # assembles the (short) parameter vector
            c = self.param_columns[e][j]
            p = self.model.params[n]
            if c is None:
                values.append(self.fixed[(n, e)].to(z).expand(z.shape[:-1]))
                continue
            key = (n, 0) if not p.per_experiment else (n, e)
            v, d = p.to_physical(z[..., c], self.scales[key].to(z))
            values.append(v)
            D[..., j, c] = d
        return torch.stack(values, -1), D

    def nodes(self, z: torch.Tensor, e: int) -> torch.Tensor:
        """(*batch, S, nx) initial states of the segments of experiment ``e``."""
        nx = self.model.nx
        if self.nodes_measured[e] is not None:
            return self.nodes_measured[e].expand(*self.batch, -1, nx)
        cols = self.x0_columns[e]
        first = z[..., cols] if cols is not None else self.known_x0[e].expand(*self.batch, nx)
        rest = []
        if self.node_columns[e] is not None:
            rest = [z[..., self.node_columns[e]].unflatten(-1, (-1, nx))]
        return torch.cat([first.unsqueeze(-2)] + rest, -2)

    def residuals_and_jacobian(self, z: torch.Tensor):
        """``r`` (*batch, M) and ``J = dr/dz`` (*batch, M, n_columns) as a
        :class:`~integrators.block_jacobian.BlockJacobian`: each segment's rows touch only the
        parameters and its own nodes (a defect also the next node's), so the normal matrix
        is block tridiagonal over the nodes with a border of parameters, formed and solved
        in linear time in the segments."""
        self.stats = []
        residuals, groups, rows, offset = [], [], [], 0
        for e, part in enumerate(self.parts):
            r, blocks, kept = self._experiment(z, e, part, True)
            residuals.append(r)
            groups += blocks
            rows.append(kept + offset)
            offset += sum(v.shape[-3] * v.shape[-2] for v, _ in blocks)
        chain = None
        if self.criterion == "multiple_shooting":  # the nodes, segment after segment
            chain = torch.cat(
                [
                    self.node_table(e, self.segments[e].starts.shape[0])
                    for e in range(len(self.parts))
                ]
            )
        J = BlockJacobian(groups, self.n_columns, torch.cat(rows), chain)
        return torch.cat(residuals, -1), J

    def residuals(self, z: torch.Tensor) -> torch.Tensor:
        """``r`` (*batch, M) alone (the same simulation without its derivatives). A data set
        whose simulation fails at ``z`` (it becomes inf/nan, or an implicit method's stage
        equations are not solved, e.g. at a far trial of a stiff parameter) gets NaN
        residuals from the failure on; the other data sets get their own numbers, and the
        line search rejects the trial of that data set alone (a non-finite loss counts as
        infinite, :func:`~integrators.newton.minimize`)."""
        self.stats = []
        return torch.cat(
            [self._experiment(z, e, part, False) for e, part in enumerate(self.parts)], -1
        )

    def _experiment(self, z, e, part, derivatives):
        model, nx, ny = self.model, self.model.nx, self.ny
        P, dP_dz = self.physical(z, e)
        nodes = self.nodes(z, e)
        # a trial point outside the representable range (e.g. exp overflow of a bounded
        # parameter) gets an infinite residual, which the line search rejects
        unusable = ~(torch.isfinite(P).all(-1) & torch.isfinite(nodes).flatten(-2).all(-1))
        P = torch.where(unusable[..., None], torch.ones_like(P), P)
        nodes = torch.where(unusable[..., None, None], torch.zeros_like(nodes), nodes)
        seg = self.segments[e]
        out = model.simulate_segments(
            P,
            nodes,
            part.u,
            part.Ts,
            part.intersample,
            seg,
            ny,
            self.method,
            derivatives,
            self.compile,
        )
        self.stats.append(out["stats"])
        S, L = seg.starts.shape[0], seg.length
        N = part.N
        idx = seg.starts[:, None] + torch.arange(L + 1)
        valid = idx <= N - 1
        err = out["y"] - part.y[..., idx.clamp(max=N - 1), :]  # (*batch, S, L+1, ny)
        if self.criterion == "one_step":
            valid &= torch.arange(L + 1)[None, :] == 1
        else:
            last = torch.zeros(S, L + 1, dtype=torch.bool)
            last[-1, -1] = True
            valid &= (torch.arange(L + 1)[None, :] < L) | last
        rows = valid[..., None].expand(S, L + 1, ny).reshape(-1)
        r = err.reshape(*err.shape[:-3], -1)[..., rows]
        r = torch.where(unusable[..., None], torch.full_like(r, math.inf), r)
        shooting = self.criterion == "multiple_shooting" and S > 1
        if shooting:  # continuity defects x_end,j - s_{j+1}, j = 0..S-2, scaled per state
            w = self.defect_weight.to(z)  # (*batch, nx)
            defect = (out["x_end"][..., :-1, :] - nodes[..., 1:, :]) * w[..., None, :]
            r_all = torch.cat([r, defect.reshape(*defect.shape[:-2], -1)], -1)
        if not derivatives:
            return r_all if shooting else r
        # row blocks of J (see residuals_and_jacobian): per segment its outputs over the free
        # parameter columns and its node's columns; per defect also the next node's columns
        free = [c for c in self.param_columns[e] if c is not None]
        dP = dP_dz[..., :, free]  # (*batch, n_params, n_free)
        table = self.node_table(e, S)
        on_params = torch.tensor(free, dtype=torch.int64).expand(S, len(free))
        Jy = torch.cat([out["dy_dP"] @ dP[..., None, None, :, :], out["dy_dx0"]], -1)
        blocks = [(Jy.flatten(-3, -2), torch.cat([on_params, table], -1))]
        kept = torch.nonzero(rows).squeeze(-1)
        if not shooting:
            return r, blocks, kept
        w = w[..., None, :, None]
        d_params = (out["dxend_dP"][..., :-1, :, :] @ dP[..., None, :, :]) * w
        d_node = out["dxend_dx0"][..., :-1, :, :] * w
        minus_eye = -torch.eye(nx, dtype=z.dtype, device=z.device) * w
        Jd = torch.cat([d_params, d_node, minus_eye.expand_as(d_node)], -1)
        blocks.append((Jd, torch.cat([on_params[:-1], table[:-1], table[1:]], -1)))
        n_out = rows.shape[0]
        kept = torch.cat([kept, torch.arange(n_out, n_out + (S - 1) * nx)])
        return r_all, blocks, kept

    def node_table(self, e: int, S: int) -> torch.Tensor:
        """(S, nx) z-columns of the segments' initial states (-1 where not free)."""
        nx = self.model.nx
        table = torch.full((S, nx), -1, dtype=torch.int64)
        if self.x0_columns[e] is not None:
            table[0] = torch.tensor(self.x0_columns[e])
        if self.node_columns[e] is not None:
            table[1:] = torch.tensor(self.node_columns[e]).reshape(S - 1, nx)
        return table


class _Monitor:
    """The progress bar over the Levenberg-Marquardt iterations of a fit (the callback of
    :func:`~integrators.newton.minimize`): one bar across all runs of the fit, showing the
    current loss summed over the data sets."""

    def __init__(self, total: int, progress):
        self.bar = progress_bar(total, "grey-box fit", progress, unit="iter")
        self.done = 0  # iterations of the finished runs
        self.last = 0  # iterations of the current run already shown

    def start_run(self) -> None:
        self.done += self.last
        self.last = 0

    def __call__(self, iteration: int, z: torch.Tensor, f: torch.Tensor) -> None:
        self.bar.update(iteration - self.last)
        self.last = iteration
        self.bar.set_postfix(loss=f"{float(f.sum()):.6g}", refresh=False)


def _minimise(problem: _Problem, z0: torch.Tensor, loss, max_iter, xtol, ftol, monitor):
    """Levenberg-Marquardt on ``sum rho(r(z))`` with the sensitivity Jacobian; a
    KeyboardInterrupt returns the last accepted iterate (status ``INTERRUPTED``)."""
    monitor.start_run()
    return minimize(
        problem.residuals,
        z0,
        method="levenberg_marquardt",
        jacobian=problem.residuals_and_jacobian,
        loss=None if loss.name == "gaussian" else loss,
        max_iter=max_iter,
        xtol=xtol,
        ftol=ftol,
        callback=monitor,
        catch_interrupt=True,
    )


def _interrupted(lm) -> bool:
    return bool((lm.status == NewtonStatus.INTERRUPTED).any())


def _check_start(problem: _Problem, z0: torch.Tensor, runs: int) -> None:
    """Raise a named error when the simulation from the start is not finite; decide the
    problem's ``compile`` (see :data:`_FIT_EVALUATIONS`) from the time of this simulation
    and the number of Levenberg-Marquardt ``runs`` on it."""
    tic = time.perf_counter()
    with torch.no_grad():
        r = problem.residuals(z0)
    seconds = time.perf_counter() - tic
    eager_budget = _compile_policy.AUTO_COMPILE_EAGER_SECONDS
    if problem.model.compile == "auto" and seconds * runs * _FIT_EVALUATIONS >= eager_budget:
        problem.compile = True
    bad = ~torch.isfinite(r).all(-1)
    if bool(bad.any()):
        idx = [tuple(i) for i in torch.nonzero(bad.reshape(bad.shape or (1,))).tolist()][:5]
        raise InputValidationError(
            f"the model's simulation from the starting values is not finite for data set(s) "
            f"{idx} ({int(bad.sum())} in all): the start makes the plant diverge (or a DAE's "
            "algebraic equations or an implicit method's stage equations have no solution). "
            "Start closer (Param values, x0), use criterion='multiple_shooting' with short "
            "segments, more substeps or an implicit method for a stiff plant."
        )


def fit_greybox(
    model: GreyBoxModel,
    data: IOData,
    *,
    method: str | None = None,
    loss: str = "gaussian",
    alpha=None,
    criterion: str = "simulation",
    x0=None,
    segment_length: int | None = None,
    max_iter: int = 100,
    xtol: float = 1e-10,
    ftol: float = 1e-12,
    progress: bool | None = None,
) -> FitResult:
    """Estimate the free parameters (and initial states) of a grey-box model; see
    :func:`sysid.fit` for the arguments and the module docstring for the criteria.

    ``progress``: a tqdm bar over the Levenberg-Marquardt iterations with the current loss
    (None: only when stderr is a terminal). A KeyboardInterrupt (Ctrl-C) during the
    iterations ends the fit with the last accepted iterate: ``converged`` is False,
    ``info["interrupted"]`` True and ``messages`` say so for the data sets still iterating.
    """
    if criterion not in CRITERIA:
        raise InputValidationError(
            f"criterion must be one of {CRITERIA} for a continuous-time model, got {criterion!r}."
        )
    if method not in (None, "gauss_newton", "mle"):
        raise InputValidationError(
            f"method {method!r} does not apply to a grey-box model: use 'gauss_newton' "
            f"(least squares) or 'mle' with a loss in {LOSSES}."
        )
    if loss not in LOSSES:
        raise InputValidationError(f"loss must be one of {LOSSES}, got {loss!r}.")
    if method == "gauss_newton" and loss != "gaussian":
        raise InputValidationError(
            f"method 'gauss_newton' minimises squared errors; use method='mle' for loss={loss!r}."
        )
    method = method or ("mle" if loss != "gaussian" else "gauss_newton")
    if x0 is not None and isinstance(x0, str) and x0 not in ("zero", "estimate"):
        raise InputValidationError(f"x0 must be 'zero', 'estimate' or a tensor, got {x0!r}.")
    if x0 is None and isinstance(model.x0, str):
        x0 = model.x0
    if not isinstance(data, IOData):
        raise InputValidationError(f"data must be IOData, got {type(data).__name__}.")
    estimate_x0 = isinstance(x0, str) and x0 == "estimate"
    if not model.free_names and not estimate_x0:
        raise InputValidationError("the model has no free parameter and x0 is not estimated.")
    problem = _Problem(model, data, criterion, x0, segment_length, None)
    z0 = problem.initial_z()
    P0, _ = problem.physical(z0, 0)
    x_start = problem.nodes(z0, 0)[..., 0, :]
    model.check_index(x_start, data.u[..., 0, :], P0)
    integrator, reason = model.choose_integrator(data.experiment_list[0], P0, x_start)
    problem.method = integrator
    shooting_runs = len(_PENALTY_CONTINUATION) if criterion == "multiple_shooting" else 0
    simulation_runs = 1 + (loss != "gaussian")
    runs = shooting_runs + simulation_runs
    _check_start(problem, z0, shooting_runs or simulation_runs)
    gauss = GaussianLoss()
    monitor = _Monitor(runs * max_iter, progress)
    with monitor.bar:
        z_sim, iterations = z0, 0
        if criterion == "multiple_shooting":
            lm, iterations = _multiple_shooting(problem, z0, gauss, max_iter, xtol, ftol, monitor)
            if _interrupted(lm):
                return _result(problem, lm, gauss, method, loss, iterations, integrator, reason)
            # polish by the simulation criterion from the fitted parameters and first node
            final = _Problem(model, data, "simulation", x0, None, integrator)
            z_sim = _carry_over(problem, final, lm.theta)
            problem = final
            _check_start(problem, z_sim, simulation_runs)
        lm = _minimise(problem, z_sim, gauss, max_iter, xtol, ftol, monitor)
        iterations = iterations + lm.iterations
        the_loss = gauss
        if loss != "gaussian" and not _interrupted(lm):
            the_loss = make_loss(loss, lm.residual, alpha)
            budget = max(max_iter, 500) if loss == "laplace" else max_iter
            lm = _minimise(problem, lm.theta, the_loss, budget, xtol, ftol, monitor)
            iterations = iterations + lm.iterations
    return _result(problem, lm, the_loss, method, loss, iterations, integrator, reason)


def _multiple_shooting(problem: _Problem, z0, loss, max_iter, xtol, ftol, monitor):
    """Penalty continuation over :data:`_PENALTY_CONTINUATION` (see the module docstring);
    returns the last run's result and the iterations of all runs."""
    y = problem.data.y
    y_scale = y.std(dim=-2).mean(-1).clamp_min(torch.finfo(y.dtype).tiny)  # (*batch,)
    with torch.no_grad():
        nodes = torch.cat([problem.nodes(z0, e) for e in range(len(problem.parts))], -2)
    # per data set (a batch member's fit must not depend on the others): unmeasured states,
    # whose node guesses are zero, get 1e-3 of the data set's largest node value
    floor = 1e-3 * nodes.abs().amax((-2, -1)).clamp_min(1.0)  # (*batch,)
    state_scale = nodes.std(dim=-2).clamp_min(floor[..., None])
    iterations, z = 0, z0
    for mu in _PENALTY_CONTINUATION:
        problem.defect_weight = math.sqrt(mu) * y_scale[..., None] / state_scale
        lm = _minimise(problem, z, loss, max_iter, xtol, ftol, monitor)
        z = lm.theta
        iterations = iterations + lm.iterations
        if _interrupted(lm):
            break
    return lm, iterations


def _carry_over(ms: _Problem, sim: _Problem, z: torch.Tensor) -> torch.Tensor:
    """The simulation problem's start from a multiple-shooting estimate: the parameters and,
    where estimated, the first node of each experiment as its initial state."""
    out = sim.initial_z()
    for c_sim, name in enumerate(sim.column_names):
        out[..., c_sim] = z[..., ms.column_names.index(name)]
    return out


def _result(problem, lm, the_loss, method, loss, iterations, integrator, reason):
    J, r, z = lm.J.dense(), lm.residual, lm.theta
    failed = lm.status == NewtonStatus.LINE_SEARCH_FAILED
    # columns of J in physical units: divide each parameter column by dp/dz
    factor_cols, phys = torch.ones_like(z), z.clone()
    at_bound, z_inside = torch.zeros_like(z, dtype=torch.bool), z.clone()
    for e in range(len(problem.parts)):
        P, dP_dz = problem.physical(z, e)
        for j, c in enumerate(problem.param_columns[e]):
            if c is not None:
                factor_cols[..., c] = dP_dz[..., j, c]
                phys[..., c] = P[..., j]
                name = problem.model.names[j]
                p = problem.model.params[name]
                start = p.start(len(problem.parts), e)
                at_bound[..., c], inside = _at_bound(P[..., j], start, p)
                scale = problem.scales[(name, e if p.per_experiment else 0)].to(z)
                z_inside[..., c] = p.to_unconstrained(inside, scale)
    # a member at a bound whose criterion decreases inside it stalled there: not a minimum
    stalled = torch.zeros_like(lm.status, dtype=torch.bool)
    if bool(at_bound.any()):
        with torch.no_grad():
            r_inside = problem.residuals(torch.where(at_bound, z_inside, z))
        lower = the_loss.rho(r_inside).sum(-1) < the_loss.rho(r).sum(-1)
        stalled = at_bound.any(-1) & lower
    J_phys = J / factor_cols.unsqueeze(-2)
    keep = problem.reported
    cov_all, sigma2, factor = covariance(J_phys, r, the_loss)
    cov = cov_all[..., keep, :][..., :, keep]
    theta = phys[..., keep]
    se = torch.diagonal(cov, dim1=-2, dim2=-1).clamp_min(0).sqrt()
    d, zstat = remaining_step(J, r, the_loss, factor)
    tiny = d.norm(dim=-1) <= math.sqrt(torch.finfo(d.dtype).eps) * (1 + z.norm(dim=-1))
    interrupted = lm.status == NewtonStatus.INTERRUPTED
    at_limit = lm.status == NewtonStatus.MAX_ITER
    converged = ((zstat <= STATIONARY_TOL) | tiny) & ~interrupted & ~stalled
    names = [problem.column_names[c] for c in keep]
    at_bound = at_bound[..., keep]
    model = problem.model
    params = {}
    for n in model.names:
        p = model.params[n]
        if p.free and not p.per_experiment:
            params[n] = theta[..., names.index(n)]
        elif p.free:  # the experiment is the last dimension, also of a single experiment
            params[n] = torch.stack(
                [
                    phys[..., problem.param_columns[e][model.names.index(n)]]
                    for e in range(len(problem.parts))
                ],
                -1,
            )
        else:
            params[n] = p.values if p.values.numel() > 1 else p.values[0]
    starts = [problem.nodes(z, e)[..., 0, :] for e in range(len(problem.parts))]
    x0_est = None
    if problem.x0_columns[0] is not None:
        x0_est = [phys[..., cols] for cols in problem.x0_columns]
    elif isinstance(problem.x0, str) and problem.x0 == "estimate":
        x0_est = starts  # one-step criterion: every step, the first too, starts measured
    messages = []
    # the fitted model holds x0 as known: a fit finishing an interrupted one estimates it again
    again = "fit(result.model, data" + (", x0='estimate')" if x0_est is not None else ")")
    for idx in [
        tuple(i) for i in torch.nonzero(~converged.reshape(converged.shape or (1,))).tolist()
    ]:
        key = idx if converged.dim() else ()
        if bool(interrupted[key]):
            why = (
                f"interrupted (KeyboardInterrupt) after {int(lm.iterations[key])} iterations of "
                f"the {problem.criterion!r} criterion; the estimate is its last accepted "
                "iterate"
            )
        elif bool(failed[key]):
            why = "the line search found no decrease"
        elif bool(stalled[key]):
            stuck = [names[k] for k in torch.nonzero(at_bound[key]).flatten().tolist()]
            why = (
                f"{', '.join(map(repr, stuck))} stalled at a bound although the criterion "
                "decreases inside it (the bounded coordinate is flat there)"
            )
        elif bool(at_limit[key]):
            why = "the iteration limit (max_iter) was reached"
        else:
            why = "it stopped away from a stationary point"
        why += (
            f"; a Gauss-Newton step would still move the estimate by "
            f"{float(zstat[key]):.3g} standard errors (converged means <= {STATIONARY_TOL})"
        )
        messages.append(
            f"batch index {key}: did not converge: {why}. "
            + (
                f"Run the fit again from it ({again}) to finish."
                if bool(interrupted[key])
                else "Start closer (or further from the bounds), raise max_iter, or use "
                "criterion='multiple_shooting'."
            )
        )
    if messages:
        warnings.warn(
            f"fit: {len(messages)} of {converged.numel()} data sets did not converge:\n  "
            + "\n  ".join(messages[:5])
            + "\n(result.messages lists them all; result.converged flags them.)",
            ConvergenceWarning,
            stacklevel=3,
        )
    messages += _bound_messages(at_bound & ~stalled[..., None], names)
    _warn_unidentifiable(cov, J_phys[..., keep], names)
    stats = problem.stats
    if x0_est is not None and len(x0_est) == 1:
        x0_est = x0_est[0]
    fitted = model.with_values(params, x0_est if x0_est is not None else problem.x0)
    quality = simulation_quality(fitted, problem.data, params, starts)
    result = FitResult(
        theta=theta,
        covariance=cov,
        standard_errors=se,
        sigma2=sigma2,
        loss_history=lm.loss_history,
        iterations=torch.as_tensor(iterations),
        converged=converged,
        method=method,
        loss=loss,
        parameter_names=names,
        n_samples=r.shape[-1],
        residuals=-r,  # r is yhat - y; the result holds the prediction errors y - yhat
        model=fitted,
        info={
            "criterion": problem.criterion,
            "integrator": integrator if isinstance(integrator, str) else integrator.name,
            "integrator_choice": reason,
            "substeps": model.substeps,
            "n_steps": sum(s.n_steps for s in stats),
            "n_f_evals": sum(s.n_f_evals for s in stats),
            "compiled": any(s.extra.get("compiled", False) for s in stats),
            "compile_fallback": next(
                (s.extra["compile_fallback"] for s in stats if s.extra.get("compile_fallback")),
                None,
            ),
            "damping": lm.damping,
            "step_in_standard_errors": zstat,
            "line_search_failed": failed,
            "iteration_limit_reached": at_limit,
            "interrupted": interrupted,
            "at_bound": at_bound,
        },
        stable=None,
        messages=messages,
        quality=quality,
    )
    result.params = params
    result.x0 = x0_est
    return result


def simulation_quality(
    model: GreyBoxModel, data: IOData, params: dict | None = None, x0=None, skip: int = 0
):
    """:class:`~sysid.validation.FitQuality` (fit %, RMSE, R^2 per data set and output
    channel) of the model's free-run simulation on ``data``, leaving out the first ``skip``
    samples of every experiment (the statistics pool the experiments of a data set).

    ``params`` and ``x0`` as in :meth:`GreyBoxModel.simulate`. A simulation that diverges
    gives non-finite statistics for its data set instead of an error.
    """
    from ..validation import _quality

    keep = data.samples_after(skip)
    yhat = model.simulate(data, params, x0)
    y = data.y.index_select(-2, keep)
    quality = _quality(y, yhat.to(y).index_select(-2, keep), 0, "validate", check=False)
    quality.skip = skip
    return quality


def _within_batch(shape, batch) -> bool:
    """Whether ``shape`` broadcasts to ``batch`` without widening it."""
    try:
        return torch.broadcast_shapes(shape, batch) == batch
    except RuntimeError:
        return False


def _at_bound(value: torch.Tensor, start: torch.Tensor, param):
    """Whether the estimate ``value`` (*batch,) of a bounded parameter ended at a bound: closer
    to it than :data:`_AT_BOUND` times the start's distance to it (the bounded coordinates
    only approach a bound as the unconstrained one goes to infinity); and a value inside,
    a tenth of that distance away from the bound it is at (``value`` elsewhere)."""
    out, inside = torch.zeros_like(value, dtype=torch.bool), value.clone()
    start = start.to(value)
    for bound in (param.min, param.max):
        if bound is not None:
            near = (value - bound).abs() <= _AT_BOUND * (start - bound).abs()
            inside = torch.where(near, bound + 0.1 * (start - bound), inside)
            out |= near
    return out, inside


def _bound_messages(at_bound: torch.Tensor, names: list[str]) -> list[str]:
    """One message per data set with an estimate at its bound (``at_bound`` (*batch, p)),
    also issued as a :class:`ParameterAtBoundWarning`."""
    messages = []
    flat = at_bound.reshape(-1, len(names))
    for idx in torch.nonzero(flat.any(-1)).flatten().tolist():
        key = tuple(int(i) for i in np.unravel_index(idx, at_bound.shape[:-1]))
        pinned = [names[k] for k in torch.nonzero(flat[idx]).flatten().tolist()]
        messages.append(
            f"batch index {key}: {', '.join(map(repr, pinned))} ended at a bound: the "
            "criterion increases inside it, so its minimum lies beyond the bound (a wrong "
            "model structure, sign or bound for these data) and the standard errors do not "
            "describe a minimum. Check the model, or widen the bound."
        )
    if messages:
        warnings.warn(
            f"fit: estimates at their bounds in {len(messages)} of {flat.shape[0]} data "
            "sets:\n  " + "\n  ".join(messages[:5]) + "\n(result.info['at_bound'] flags them.)",
            ParameterAtBoundWarning,
            stacklevel=4,
        )
    return messages


def _warn_unidentifiable(cov: torch.Tensor, J: torch.Tensor, names: list[str]) -> None:
    """PoorExcitationWarning naming the most correlated pair of estimates when it is
    (nearly) perfectly correlated in some data set; where the covariance is singular (inf),
    the estimates of the direction in which the scaled Jacobian ``J`` (*batch, M, p) of
    their columns is flattest (its smallest right singular vector)."""
    p = cov.shape[-1]
    if p < 2:
        return
    singular = ~torch.isfinite(torch.diagonal(cov, dim1=-2, dim2=-1)).all(-1)
    if bool(singular.any()):
        nameable = singular & torch.isfinite(J).flatten(-2).all(-1)
        if not bool(nameable.any()):  # a non-finite Jacobian: covariance() warned already
            return
        member = J[nameable][0]  # the first singular data set with a finite J, (M, p)
        scaled = member / member.norm(dim=-2, keepdim=True).clamp_min(torch.finfo(J.dtype).tiny)
        v = torch.linalg.svd(scaled, full_matrices=False).Vh[-1].abs()
        involved = [names[k] for k in torch.nonzero(v > 0.1 * v.max()).flatten().tolist()]
        warnings.warn(
            f"the estimates of {', '.join(map(repr, involved))} enter the data only in a "
            "combination (the normal matrix is singular along it): the data cannot tell them "
            "apart. Fix all but one of them (Param(..., free=False)), or use an input that "
            "excites the plant more richly.",
            PoorExcitationWarning,
            stacklevel=4,
        )
        return
    sd = torch.diagonal(cov, dim1=-2, dim2=-1).clamp_min(torch.finfo(cov.dtype).tiny).sqrt()
    corr = cov / (sd.unsqueeze(-1) * sd.unsqueeze(-2))
    corr = torch.nan_to_num(corr, nan=1.0, posinf=1.0, neginf=-1.0)
    off = corr.abs() * (1 - torch.eye(p, dtype=cov.dtype, device=cov.device))
    worst = off.reshape(-1, p * p).amax(0).reshape(p, p)
    value = float(worst.max())
    if value > _IDENTIFIABILITY_CORRELATION:
        i, j = np.unravel_index(int(worst.argmax()), (p, p))
        warnings.warn(
            f"the estimates of {names[i]!r} and {names[j]!r} are correlated at |r| = "
            f"{value:.6f}: the data cannot tell them apart (only a combination is "
            "identifiable). Fix one of them (Param(..., free=False)), or use an input that "
            "excites the plant more richly.",
            PoorExcitationWarning,
            stacklevel=4,
        )
