"""Result objects shared by every integrator: per-sample status, statistics, Solution."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum

import torch

from .errors import InputValidationError


class Status(IntEnum):
    """Per-sample outcome of an integration, stored as int8 codes in ``Solution.status``."""

    SUCCESS = 0
    MAX_STEPS = 1  # the step budget ran out before the last output time
    NON_FINITE = 2  # the state or its derivative became inf/nan (e.g. finite escape time)
    NEWTON_FAILED = 3  # an implicit stage solve did not converge, even after step reduction
    STEP_TOO_SMALL = 4  # the step size fell below the resolution of the time variable


@dataclass
class SolverStats:
    """Work counters. Each is an int for the whole batch or a (*batch,) int64 tensor.

    Attributes:
        n_f_evals: right-hand-side evaluations (one batched call counts once).
        n_steps: accepted steps.
        n_rejected: rejected steps (error too large or Newton failure).
        n_newton_iters: Newton iterations over all implicit stage solves.
        n_factorizations: LU/Cholesky factorisations of iteration matrices.
        n_jac_evals: Jacobian evaluations.
        extra: anything method-specific (e.g. the choice made by method="auto").
    """

    n_f_evals: int | torch.Tensor = 0
    n_steps: int | torch.Tensor = 0
    n_rejected: int | torch.Tensor = 0
    n_newton_iters: int | torch.Tensor = 0
    n_factorizations: int | torch.Tensor = 0
    n_jac_evals: int | torch.Tensor = 0
    extra: dict = field(default_factory=dict)


@dataclass
class Solution:
    """The result of ``odeint`` / ``daeint``.

    Failures are per sample and never raise: a sample whose integration stops (a step or
    Newton failure, a step below the time resolution, a non-finite state, the step budget, a
    DAE losing index 1) gets a non-SUCCESS ``status`` and a message naming its index and the
    time ``t_f`` where it stopped, and all its outputs (``x``, ``z`` and dense output) at times
    after ``t_f`` are NaN; every solver (explicit, adaptive, implicit, ``daeint``) follows this
    rule. Its outputs up to ``t_f`` and the other samples are unaffected, and so are their
    gradients: a loss over the finite outputs has finite, correct gradients.

    Attributes:
        t: (T,) output times.
        x: (*batch, T, nx) differential states at ``t``.
        z: (*batch, T, nz) algebraic states (DAEs only), else None.
        status: (*batch,) int8 tensor of :class:`Status` codes.
        stats: :class:`SolverStats`.
        messages: human-readable reasons for every sample whose status is not SUCCESS,
            naming the sample index and the time where it stopped.
        method: the name of the method that produced the solution.
        interpolant: callable ``t -> (*batch, len(t), nx)`` for dense output, or None.
    """

    t: torch.Tensor
    x: torch.Tensor
    status: torch.Tensor
    stats: SolverStats
    z: torch.Tensor | None = None
    messages: list[str] = field(default_factory=list)
    method: str = ""
    interpolant: Callable[[torch.Tensor], torch.Tensor] | None = None

    @property
    def success(self) -> bool:
        """True when every sample reached the final time."""
        return bool(torch.all(self.status == Status.SUCCESS))

    def at(self, t) -> torch.Tensor:
        """Dense output: the states at arbitrary times inside the integration interval.

        Args:
            t: scalar or (M,) tensor of times in ``[t[0], t[-1]]`` (a few rounding errors
                outside count as the end points).

        Returns:
            (*batch, M, nx) states (M = 1 for a scalar time).

        Raises:
            InputValidationError: no dense output for this method, or non-finite times or
                times outside the integration interval (the interpolants do not
                extrapolate).
        """
        if self.interpolant is None:
            raise InputValidationError(
                f"method {self.method!r} has no dense output; use an adaptive method "
                "('dopri5') or a collocation method, or request the times in `t`."
            )
        t = torch.as_tensor(t, dtype=self.t.dtype, device=self.t.device).reshape(-1)
        check_query_times(t, float(self.t[0]), float(self.t[-1]))
        return self.interpolant(t)


def check_query_times(tq: torch.Tensor, t0: float, t_end: float) -> None:
    """Raise InputValidationError unless every time of ``tq`` (M,) is finite and inside
    ``[t0, t_end]``, up to 8 rounding errors of the largest time involved (one host
    synchronisation)."""
    if tq.numel() == 0:
        return
    q = tq.detach()
    slack = 8.0 * torch.finfo(q.dtype).eps * max(abs(t0), abs(t_end), t_end - t0)
    bad = ~torch.isfinite(q) | (q < t0 - slack) | (q > t_end + slack)
    if not bool(bad.any()):
        return
    k = int(torch.nonzero(bad)[0])
    raise InputValidationError(
        f"dense output requested at t[{k}] = {float(q[k])}, but the solution covers "
        f"[{t0:.10g}, {t_end:.10g}]; the interpolant does not extrapolate: pass finite times "
        "inside the integration interval."
    )
