"""Classic ODE test problems of the notes, as ``sysid.zoo`` plants.

Each plant is a ``torch.nn.Module`` whose ``forward(t, x, u=None) -> xdot`` can be passed
directly as ``f`` to ``integrators.odeint``. States have shape ``(*batch, nx)``; ``t`` is a
0-dim tensor or ``(*batch, 1)`` and is ignored by these autonomous plants. Parameters are
``nn.Parameter`` that broadcast against the batch (see ``_params``). Where a closed-form
solution exists, ``exact(t, x0)`` returns it with shape ``(*batch, len(t), nx)``, the layout of
``Solution.x``. ``state_names`` lists the state components in order (the first line of each
class docstring gives the same order).
"""

import torch
from torch import nn

from integrators.errors import InputValidationError

from ._params import (
    as_parameter,
    check_state,
    input_or_zero,
    like,
    like_component,
    per_member,
    stack_components,
)


def _time_grid(t, x0: torch.Tensor) -> torch.Tensor:
    t = torch.as_tensor(t, dtype=x0.dtype, device=x0.device)
    if t.dim() != 1:
        raise InputValidationError(
            f"exact(): t must be a 1-D time grid, got shape {tuple(t.shape)}"
        )
    return t


class VanDerPol(nn.Module):
    """Van der Pol oscillator, state (x1, x2) = (velocity x2', position x2): eq. (6.43)'s order.

    x1' = mu (1 - x2^2) x1 - x2 + u,   x2' = x1,

    with mu = 1 giving eq. (6.43) exactly (and, with u, the dynamics of eq. 1.37). The first
    component is the velocity-like one, the second the position: the reverse of the usual
    (position, velocity) order (and of :class:`StiffVanDerPol`). The input u (*batch, 1) is an
    optional force on x1 (zero when None). Not stiff for mu = O(1).
    """

    nx = 2
    nu = 1
    state_names = ("x1", "x2")

    def __init__(self, mu=1.0):
        super().__init__()
        self.mu = as_parameter(mu, "mu")

    def forward(self, t, x, u=None):
        check_state(x, 2, "VanDerPol")
        mu = like_component(self.mu, x)
        x1, x2 = x.unbind(-1)
        x1_dot = mu * (1 - x2 * x2) * x1 - x2
        if u is not None:
            x1_dot = x1_dot + input_or_zero(u, x, 1)[..., 0]
        return stack_components(x1_dot, x1)


class StiffVanDerPol(nn.Module):
    """Stiff Van der Pol oscillator, state (y1, y2) = (position, velocity y1'), epsilon scaling:

    y1' = y2,   eps y2' = (1 - y1^2) y2 - y1,

    stiff for small eps (default 1e-6): the fast variable y2 relaxes on a time scale eps to the
    slow manifold y2 = y1 / (1 - y1^2) (the DAE limit of Theorem 8, §5.4). eps must be > 0
    (InputValidationError).
    """

    nx = 2
    state_names = ("y1", "y2")

    def __init__(self, eps=1e-6):
        super().__init__()
        self.eps = as_parameter(eps, "eps", positive=True)

    def forward(self, t, x, u=None):
        check_state(x, 2, "StiffVanDerPol")
        eps = like_component(self.eps, x)
        y1, y2 = x.unbind(-1)
        return stack_components(y2, ((1 - y1 * y1) * y2 - y1) / eps)


class Lorenz(nn.Module):
    """Lorenz system, state (x1, x2, x3), eq. (6.9):

    x1' = sigma (x2 - x1), x2' = x1 (rho - x3) - x2, x3' = x1 x2 - beta x3. Defaults are the
    classic sigma = 10, rho = 28, beta = 8/3 (the notes use beta = 3 with x0 = [1, 1, 1] for
    Fig. 6.2-6.5; pass ``beta=3.0`` to reproduce them)."""

    nx = 3
    state_names = ("x1", "x2", "x3")

    def __init__(self, sigma=10.0, rho=28.0, beta=8.0 / 3.0):
        super().__init__()
        self.sigma = as_parameter(sigma, "sigma")
        self.rho = as_parameter(rho, "rho")
        self.beta = as_parameter(beta, "beta")

    def forward(self, t, x, u=None):
        check_state(x, 3, "Lorenz")
        sigma, rho, beta = (like_component(p, x) for p in (self.sigma, self.rho, self.beta))
        x1, x2, x3 = x.unbind(-1)
        return stack_components(sigma * (x2 - x1), x1 * (rho - x3) - x2, x1 * x2 - beta * x3)


class StiffLinear(nn.Module):
    """Stiff linear system of eq. (6.42), state (x1, x2, x3, x4), x' = A(eps) x, stiff reading:

        A = [[0,      5,      1,        0      ],
             [-5,     0,      0,        1/2    ],
             [0,      0,      -0.1/eps, 1/eps  ],
             [0,      1/eps,  -1/eps,   -0.1/eps]].

    Typo in the notes: eq. (6.42) as typed multiplies the fast block by eps = 5e-4, which makes
    x3, x4 *slow* (eigenvalues ~ -5e-5 +- 5e-4 i) and contradicts Fig. 6.16 (RK4 stable only up
    to dt ~ 1.5e-3). Dividing by eps instead gives the fast eigenvalues (-0.1 +- i)/eps =
    -200 +- 2000 i, and RK4 with dt = 1.5e-3 then sits at lambda dt = -0.3 +- 3i, on the edge of
    its stability region, exactly as the figure says. This is the singularly perturbed form
    eps z' = g(x, z) of eq. (5.33) with x = (x1, x2), z = (x3, x4). eps must be > 0
    (InputValidationError).
    """

    nx = 4
    state_names = ("x1", "x2", "x3", "x4")

    def __init__(self, eps=5e-4):
        super().__init__()
        self.eps = as_parameter(eps, "eps", positive=True)

    def matrix(self, like_tensor: torch.Tensor | None = None) -> torch.Tensor:
        """A(eps), shape (*pb, 4, 4) for a tensor eps of shape (*pb, 1), (4, 4) for a scalar."""
        eps = self.eps if like_tensor is None else like(self.eps, like_tensor)
        e = 1.0 / per_member(eps)
        zero, one = torch.zeros_like(e), torch.ones_like(e)
        rows = [
            [zero, 5 * one, one, zero],
            [-5 * one, zero, zero, 0.5 * one],
            [zero, zero, -0.1 * e, e],
            [zero, e, -e, -0.1 * e],
        ]
        return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)

    def forward(self, t, x, u=None):
        check_state(x, 4, "StiffLinear")
        return (self.matrix(x) @ x.unsqueeze(-1)).squeeze(-1)

    def exact(self, t, x0):
        """x(t) = expm(A t) x0 on the grid t (T,), shape (*batch, T, 4)."""
        check_state(x0, 4, "StiffLinear")
        t = _time_grid(t, x0)
        a = self.matrix(x0).unsqueeze(-3)  # (*pb, 1, 4, 4)
        phi = torch.linalg.matrix_exp(a * t[:, None, None])  # (*pb, T, 4, 4)
        return (phi @ x0[..., None, :, None]).squeeze(-1)


class LinearTestEquation(nn.Module):
    """Dahlquist test equation, state x (one entry per entry of lam), x' = lam x, eq. (6.40).

    Exact solution x0 exp(lam t). A scalar lam (or one of shape (*batch, 1)) acts on each
    component of a state of any width; ``nx`` and ``state_names`` describe the default
    single-component state ``x``, or ``x1..xn`` for lam of shape (..., n), n > 1.
    """

    def __init__(self, lam=-1.0):
        super().__init__()
        self.lam = as_parameter(lam, "lam", vector=True)

    @property
    def nx(self) -> int:
        return self.lam.shape[-1] if self.lam.dim() else 1

    @property
    def state_names(self) -> tuple[str, ...]:
        return ("x",) if self.nx == 1 else tuple(f"x{i + 1}" for i in range(self.nx))

    def forward(self, t, x, u=None):
        return like(self.lam, x) * x

    def exact(self, t, x0):
        """x0 exp(lam t) on the grid t (T,), shape (*batch, T, nx)."""
        t = _time_grid(t, x0)
        lam = like(self.lam, x0)
        lam = lam.unsqueeze(-2) if lam.dim() >= 1 else lam
        return x0.unsqueeze(-2) * torch.exp(lam * t[:, None])


class Quadratic(nn.Module):
    """Scalar state x, x' = x^2, eq. (1.44): finite escape time 1/x0 for x0 > 0.

    Exact solution x0 / (1 - x0 t) (eq. 1.45 is the case x0 = 1)."""

    nx = 1
    state_names = ("x",)

    def forward(self, t, x, u=None):
        return x**2

    @staticmethod
    def escape_time(x0: torch.Tensor) -> torch.Tensor:
        """1/x0 where x0 > 0, +inf otherwise (the solution exists on [0, escape_time))."""
        return torch.where(x0 > 0, 1.0 / x0, torch.full_like(x0, float("inf")))

    def exact(self, t, x0):
        """x0 / (1 - x0 t), shape (*batch, T, nx); raises where some t reaches the escape time."""
        t = _time_grid(t, x0)
        escape = self.escape_time(x0)  # (*batch, nx)
        if t.numel() and bool((t.max() >= escape).any()):
            bad = (t.max() >= escape).nonzero()[0].tolist()
            raise InputValidationError(
                f"Quadratic.exact: the solution from x0 at index {bad} escapes to infinity at "
                f"t = {float(escape[tuple(bad)]):.6g} <= max(t) = {float(t.max()):.6g}; "
                "shorten the time grid"
            )
        x0 = x0.unsqueeze(-2)
        return x0 / (1 - x0 * t[:, None])


class SqrtAbs(nn.Module):
    """Scalar state x, ``x' = sqrt(|x|)``, eq. (1.46): solutions through x = 0 are not unique.

    ``exact(t, x0, dwell=0)`` returns the solution that, on reaching x = 0 (or starting there),
    rests there for ``dwell`` time units and then leaves as ((t - t0)/2)^2 (eq. 1.47 with
    t0 = arrival + dwell). For x0 > 0 the solution (sqrt(x0) + t/2)^2 is unique.
    """

    nx = 1
    state_names = ("x",)

    def forward(self, t, x, u=None):
        return torch.sqrt(torch.abs(x))

    def exact(self, t, x0, dwell=0.0):
        t = _time_grid(t, x0)[:, None]
        x0 = x0.unsqueeze(-2)
        root = torch.sqrt(torch.abs(x0))
        positive = x0 > 0
        arrival = torch.where(positive, torch.zeros_like(x0), 2 * root)  # time x reaches 0
        leave = arrival + dwell
        before = -((root - t / 2) ** 2)  # approach from below, valid for t < arrival
        after = torch.where(positive, (root + t / 2) ** 2, (torch.relu(t - leave) / 2) ** 2)
        return torch.where(~positive & (t < arrival), before, after)


class NonlinearExample(nn.Module):
    """The example of §1.7, state (x1, x2) = (velocity x2', position x2), as in eq. (1.37):

    x1' = (1 - x2^2) x1 - x2 + u (eq. 1.37a), x2' = x1 (eq. 1.37b), output
    y = h(x) = x1 + x2^3 (eq. 1.38). Steady states x = [0, u_bar] (eq. 1.41)."""

    nx = 2
    state_names = ("x1", "x2")
    nu = 1
    ny = 1

    def forward(self, t, x, u=None):
        check_state(x, 2, "NonlinearExample")
        x1, x2 = x[..., 0:1], x[..., 1:2]
        u = input_or_zero(u, x, 1)
        return torch.cat([(1 - x2**2) * x1 - x2 + u, x1], dim=-1)

    def output(self, x, u=None):
        """y = x1 + x2^3, eq. (1.38), shape (*batch, 1)."""
        check_state(x, 2, "NonlinearExample")
        return x[..., 0:1] + x[..., 1:2] ** 3

    @staticmethod
    def steady_state(u_bar: torch.Tensor) -> torch.Tensor:
        """x_bar = [0, u_bar] of eq. (1.41) for u_bar of shape (*batch, 1)."""
        return torch.cat([torch.zeros_like(u_bar), u_bar], dim=-1)

    @staticmethod
    def closed_form_linearization(x: torch.Tensor):
        """A, B, C, D of eq. (1.39) at states x (*batch, 2) (eq. 1.42 at x = [0, u_bar])."""
        x1, x2 = x[..., 0], x[..., 1]
        one, zero = torch.ones_like(x1), torch.zeros_like(x1)
        a = torch.stack(
            [torch.stack([1 - x2**2, -2 * x1 * x2 - 1], -1), torch.stack([one, zero], -1)], -2
        )
        b = torch.stack([one, zero], -1).unsqueeze(-1)
        c = torch.stack([one, 3 * x2**2], -1).unsqueeze(-2)
        d = zero[..., None, None]
        return a, b, c, d
