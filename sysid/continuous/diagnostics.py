"""Long-rollout diagnostics of a learned continuous-time model against the true system.

A model that fits short windows may still drift away over a long horizon. Its free rollout
from an initial state is compared with the true system's on the same grid, and that error is
read against a floor: how far the true system itself moves apart when its initial state is
perturbed by ``perturbation`` (default 1e-4, added to every component). Where the floor grows
(a chaotic or unstable plant), no model can stay closer than it; where it stays flat (a
conservative oscillator), a growing model error is the model's. For conservative plants the
true energy evaluated along the model's rollout measures its drift,
``(E(x(t)) - E(x0)) / |E(x0)|``: zero for an energy-conserving flow.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from integrators import odeint
from integrators.errors import InputValidationError

__all__ = ["RolloutDiagnostics", "rollout_diagnostics"]


@dataclass
class RolloutDiagnostics:
    """The result of :func:`rollout_diagnostics`.

    Attributes:
        t: (T,) the grid.
        x: (*batch, T, nx) the model's rollout.
        x_true: (*batch, T, nx) the true system's.
        error: (*batch, T) Euclidean state error ``||x - x_true||``.
        floor: (*batch, T) ``||x_true(x0 + delta) - x_true(x0)||``, the true system's own
            divergence from the perturbed initial state.
        energy: (*batch, T) relative change of the true energy along the model's rollout,
            ``(E(x(t)) - E(x0)) / |E(x0)|``; None without an energy function.
    """

    t: torch.Tensor
    x: torch.Tensor
    x_true: torch.Tensor
    error: torch.Tensor
    floor: torch.Tensor
    energy: torch.Tensor | None

    def summary(self) -> dict[str, torch.Tensor]:
        """Per rollout (*batch,): ``rms_error`` and ``final_error`` of the state,
        ``rms_floor``, their ratio ``error_over_floor`` (root mean squares over the grid)
        and, with an energy function, ``energy_drift`` = ``max_t |energy|``."""
        rms = self.error.square().mean(-1).sqrt()
        rms_floor = self.floor.square().mean(-1).sqrt()
        out = {
            "rms_error": rms,
            "final_error": self.error[..., -1],
            "rms_floor": rms_floor,
            "error_over_floor": rms / rms_floor,
        }
        if self.energy is not None:
            out["energy_drift"] = self.energy.abs().amax(-1)
        return out


def rollout_diagnostics(
    model: Callable,
    true_rhs: Callable,
    x0: torch.Tensor,
    t: torch.Tensor,
    *,
    energy: Callable | None = None,
    perturbation: float = 1e-4,
    u=None,
    method: str = "rk4",
    substeps: int = 1,
    true_method: str = "rk4",
    true_substeps: int = 10,
) -> RolloutDiagnostics:
    """Roll a model out from ``x0`` over the grid ``t`` and compare it with the true system.

    Args:
        model: the learned right-hand side ``f(t, x[, u])`` (a function or ``nn.Module``, e.g.
            a trained :class:`~sysid.continuous.NeuralODE`), integrated by ``method`` with
            ``substeps`` fixed steps per interval of ``t``.
        true_rhs: the true system's right-hand side, same signature, integrated by
            ``true_method`` with ``true_substeps`` steps per interval (finer: the reference).
        x0: (*batch, nx) initial states.
        t: (T,) increasing grid (seconds).
        energy: ``E(x) -> (*batch,)`` of states (*batch, nx), the true plant's energy; None:
            no energy diagnostic.
        perturbation: added to every component of ``x0`` for the floor (> 0).
        u: the input, as :func:`integrators.odeint` takes it (None for autonomous systems).
        method, substeps, true_method, true_substeps: fixed-step methods (names of
            :func:`integrators.odeint`) and steps per interval of the model and of the truth.

    Returns:
        :class:`RolloutDiagnostics`; its ``summary()`` gives the root-mean-square error, the
        floor, their ratio and the largest energy drift per rollout.

    Raises:
        InputValidationError: ``perturbation <= 0``, ``x0`` not of shape (*batch, nx), an
            energy function returning the wrong shape or zero energy at ``x0``.
    """
    if not perturbation > 0:
        raise InputValidationError(
            f"perturbation must be > 0 (the size of the floor's initial offset), got "
            f"{perturbation!r}."
        )
    if not isinstance(x0, torch.Tensor) or x0.dim() < 1:
        raise InputValidationError("x0 must be a tensor of shape (*batch, nx).")
    with torch.no_grad():
        x = odeint(model, x0, t, method=method, substeps=substeps, adaptive=False, u=u).x
        both = torch.stack([x0, x0 + perturbation])
        truth = odeint(
            true_rhs, both, t, method=true_method, substeps=true_substeps, adaptive=False, u=u
        ).x
    x_true = truth[0]
    rel_energy = None
    if energy is not None:
        with torch.no_grad():
            e = energy(x)
            e0 = energy(x0)
        if e.shape != x.shape[:-1] or e0.shape != x0.shape[:-1]:
            raise InputValidationError(
                f"energy(x) must return one value per state (*batch,), got {tuple(e0.shape)} "
                f"for x0 of shape {tuple(x0.shape)}."
            )
        if bool((e0 == 0).any()):
            raise InputValidationError(
                "the energy is zero at x0: the relative drift is not defined; shift the "
                "energy's reference (e.g. E + 1) or start away from the rest state."
            )
        rel_energy = (e - e0[..., None]) / e0.abs()[..., None]
    return RolloutDiagnostics(
        t=t,
        x=x,
        x_true=x_true,
        error=(x - x_true).norm(dim=-1),
        floor=(truth[1] - x_true).norm(dim=-1),
        energy=rel_energy,
    )
