"""DAE examples of the notes (chapter 5) and the singularly perturbed plants of §5.3.

Fully implicit examples expose ``residual(t, xdot, x, z[, u])`` (z of width 0 when there are no
algebraic states); semi-explicit ones ``f(t, x, z[, u])`` and ``g(t, x, z[, u])`` (the
conventions of ``integrators.problems``) and the index the notes give (``index``). Singularly
perturbed plants are ODE modules (``forward(t, s, u=None)``) with ``dae_limit()``.
``state_names`` lists the (differential) states in order and ``algebraic_names`` the
algebraic ones z; the first line of each class docstring gives the same order.
"""

import torch
from torch import nn

from integrators.errors import InputValidationError

from ._params import as_parameter, cat_columns, input_or_zero, like


def _u(u, x):
    return input_or_zero(u, x, 1)


class AlgebraicStateDAE(nn.Module):
    """Eq. (5.2) as F(xdot, x) = 0 in the state (x1, x2) (eq. 5.8), no algebraic state z:

    a linear DAE whose x2 never appears differentiated (first example of the notes' §5.1).
    xdot1 = 2 x1 + x2, 0 = 3 x1 - x2; dF/dxdot = [[1, 0], [0, 0]] is singular (eq. 5.9): a DAE.
    Semi-explicit form eq. (5.12)."""

    nx, nz, index = 2, 0, 1
    state_names, algebraic_names = ("x1", "x2"), ()

    def residual(self, t, xdot, x, z, u=None):
        return torch.stack(
            [xdot[..., 0] - 2 * x[..., 0] - x[..., 1], 3 * x[..., 0] - x[..., 1]], -1
        )


class SingularMassMatrixDAE(nn.Module):
    """Eq. (5.3) as F(xdot, x) = 0 in the state (x1, x2), no algebraic state z:

    a linear DAE (second example of the notes' §5.1) in which both derivatives appear, but
    dF/dxdot = [[1, 1], [2, 2]] is singular (eq. 5.11): a DAE; the combination -2 (5.3a) + (5.3b)
    gives -3 x1 = 0 (eq. 5.4b)."""

    nx, nz, index = 2, 0, 1
    state_names, algebraic_names = ("x1", "x2"), ()

    def residual(self, t, xdot, x, z, u=None):
        x1, x2, v1, v2 = x[..., 0], x[..., 1], xdot[..., 0], xdot[..., 1]
        return torch.stack([v1 + 2 * x1 + v2 + x2, 2 * v1 + x1 + 2 * v2 + 2 * x2], -1)


class LinearIndex1DAE(nn.Module):
    """Eq. (5.46), state (x1, x2), algebraic z: F = [xdot1 - z, xdot2 - x1, xdot1 + x2 - u].

    A linear fully implicit DAE of index 1 (example of the notes' §5.4), solved for xdot and
    z in eq. (5.47)."""

    nx, nz, nu, index = 2, 1, 1, 1
    state_names, algebraic_names = ("x1", "x2"), ("z",)

    def residual(self, t, xdot, x, z, u=None):
        u = _u(u, x)[..., 0]
        return torch.stack(
            [xdot[..., 0] - z[..., 0], xdot[..., 1] - x[..., 0], xdot[..., 0] + x[..., 1] - u], -1
        )


class LinearIndex3DAE(nn.Module):
    """Eq. (5.48), state (x1, x2), algebraic z: F = [xdot1 - z, xdot2 - x1, x2 - u].

    A linear fully implicit DAE of index 3 (example of the notes' §5.4): three time
    differentiations reach an ODE (eq. 5.62-5.67)."""

    nx, nz, nu, index = 2, 1, 1, 3
    state_names, algebraic_names = ("x1", "x2"), ("z",)

    def residual(self, t, xdot, x, z, u=None):
        u = _u(u, x)[..., 0]
        return torch.stack([xdot[..., 0] - z[..., 0], xdot[..., 1] - x[..., 0], x[..., 1] - u], -1)


class LinearIndex2DAE(nn.Module):
    """Eq. (5.81), state (x1, x2), algebraic (z1, z2): xdot = (x2 + z2, z1 + u), index 2.

    A linear semi-explicit DAE (index-reduction example of the notes' §5.6).
    0 = (x1 - x2, z2 - x1); its reduction (eq. 5.86) replaces x1 - x2 by x2 + z2 - z1 - u —
    with u constant, as here; the notes' eq. (5.85) keeps the -u that comes from substituting
    xdot2 = z1 + u."""

    nx, nz, nu, index = 2, 2, 1, 2
    state_names, algebraic_names = ("x1", "x2"), ("z1", "z2")

    def f(self, t, x, z, u=None):
        u = _u(u, x)[..., 0]
        return torch.stack([x[..., 1] + z[..., 1], z[..., 0] + u], -1)

    def g(self, t, x, z, u=None):
        return torch.stack([x[..., 0] - x[..., 1], z[..., 1] - x[..., 0]], -1)

    def reduced_g(self, t, x, z, u=None):
        """g~ of eq. (5.86b)."""
        u = _u(u, x)[..., 0]
        return torch.stack([x[..., 1] + z[..., 1] - z[..., 0] - u, z[..., 1] - x[..., 0]], -1)


class UnitSphereDAE(nn.Module):
    """Eq. (5.88), state (x1, .., xn) (x1, x2 by default), algebraic z: xdot = A x - b z.

    Linear dynamics held on the unit sphere by the algebraic input z acting along b (example of
    the notes' §5.6). Constraint 0 = (x^T x - 1)/2, index 2; reduced g~ = x^T (A x - b z)
    (eq. 5.90, 5.93) with z = x^T A x / x^T b (eq. 5.92). A (n, n) and b (n,) are parameters."""

    nz, index = 1, 2
    algebraic_names = ("z",)

    def __init__(self, A=((0.0, 1.0), (-1.0, -0.5)), b=(1.0, 0.5)):
        super().__init__()
        self.A = as_parameter(A, "A", vector=True)
        self.b = as_parameter(b, "b", vector=True)
        n = self.A.shape[-1] if self.A.dim() == 2 else 0
        if n == 0 or self.A.shape != (n, n) or self.b.shape != (n,):
            raise InputValidationError(
                f"UnitSphereDAE: A must be a square (n, n) matrix and b an (n,) vector, n >= 1, "
                f"got A of shape {tuple(self.A.shape)} and b of shape {tuple(self.b.shape)}."
            )
        self.nx = n
        self.state_names = tuple(f"x{i + 1}" for i in range(self.nx))

    def f(self, t, x, z, u=None):
        a, b = like(self.A, x), like(self.b, x)
        return x @ a.T - z * b

    def g(self, t, x, z, u=None):
        return 0.5 * ((x * x).sum(-1, keepdim=True) - 1)

    def reduced_g(self, t, x, z, u=None):
        return (x * self.f(t, x, z)).sum(-1, keepdim=True)  # eq. (5.93b)

    def multiplier(self, x):
        a, b = like(self.A, x), like(self.b, x)
        return ((x @ a.T) * x).sum(-1, keepdim=True) / (x * b).sum(-1, keepdim=True)  # (5.92)


class TwoMassSystem(nn.Module):
    """Two masses with friction and springs, eq. (5.41), state s = (x1, x2, x1dot, x2dot):

    m1 x1'' = K (x2 - x1) - K x1 - rho x1' + u, m2 x2'' = K (x1 - x2) - rho x2'.

    Reductions (Fig. 5.3): m1 -> 0 gives eq. (5.42)-(5.43), the ODE
    (rho/K) x1' = x2 - 2 x1 + u/K (``ode_543``, s = (x1, x2, x2dot)); rho/K -> 0 gives the DAE
    (5.44) with x1 algebraic: 0 = x2 - 2 x1 + u/K (``f_544``/``g_544``, x = (x2, x2dot),
    z = x1). Typo fixed: eq. (5.43a) and (5.44a) divide eq. (5.42a) by K but keep u; it is u/K.
    The masses m1, m2 and the stiffness K must be > 0 (InputValidationError).
    """

    nx, nu = 4, 1
    state_names = ("x1", "x2", "x1dot", "x2dot")

    def __init__(self, m1=1e-2, m2=1.0, K=1e3, rho=1.0):
        super().__init__()
        self.m1 = as_parameter(m1, "m1", positive=True)
        self.m2 = as_parameter(m2, "m2", positive=True)
        self.K, self.rho = as_parameter(K, "K", positive=True), as_parameter(rho, "rho")

    def forward(self, t, s, u=None):
        m1, m2, k, rho = (like(p, s) for p in (self.m1, self.m2, self.K, self.rho))
        x1, x2, v1, v2 = (s[..., i : i + 1] for i in range(4))
        a1 = (k * (x2 - x1) - k * x1 - rho * v1 + _u(u, s)) / m1
        a2 = (k * (x1 - x2) - rho * v2) / m2
        return cat_columns(v1, v2, a1, a2)

    def ode_543(self, t, s, u=None):
        """Eq. (5.43) in s = (x1, x2, x2dot)."""
        m2, k, rho = (like(p, s) for p in (self.m2, self.K, self.rho))
        x1, x2, v2 = s[..., 0:1], s[..., 1:2], s[..., 2:3]
        return torch.cat(
            [k / rho * (x2 - 2 * x1 + _u(u, s) / k), v2, (k * (x1 - x2) - rho * v2) / m2], -1
        )

    def f_544(self, t, x, z, u=None):
        """Differential part of eq. (5.44b): x = (x2, x2dot), z = x1."""
        m2, k, rho = (like(p, x) for p in (self.m2, self.K, self.rho))
        x2, v2 = x[..., 0:1], x[..., 1:2]
        return cat_columns(v2, (k * (z - x2) - rho * v2) / m2)

    def g_544(self, t, x, z, u=None):
        """Algebraic part eq. (5.44a) (typo fixed): 0 = (x2 - x1) - x1 + u / K."""
        return x[..., 0:1] - 2 * z + _u(u, x) / like(self.K, x)


class SingularlyPerturbedLinear(nn.Module):
    """Eq. (5.36) as an ODE in the state (x1, x2): x1' = -x1 + x2, eps x2' = x1 - a x2 + u.

    Its limit eps -> 0 is the DAE (5.37) and, for a != 0, the ODE (5.38) with x2 = (x1 + u)/a.
    Theorem 8 applies for a > 0. eps must be > 0 (InputValidationError)."""

    nx, nu = 2, 1
    state_names = ("x1", "x2")

    def __init__(self, eps=1e-2, a=2.0):
        super().__init__()
        self.eps, self.a = as_parameter(eps, "eps", positive=True), as_parameter(a, "a")

    def forward(self, t, x, u=None):
        eps, a = like(self.eps, x), like(self.a, x)
        x1, x2 = x[..., 0:1], x[..., 1:2]
        return cat_columns(-x1 + x2, (x1 - a * x2 + _u(u, x)) / eps)

    def f(self, t, x, z, u=None):
        """DAE limit (5.37a) with x = x1, z = x2."""
        return -x + z

    def g(self, t, x, z, u=None):
        """DAE limit (5.37b)."""
        return x - like(self.a, x) * z + _u(u, x)

    def reduced(self, t, x1, u=None):
        """Eq. (5.38a): x1' = (1/a - 1) x1 + u / a."""
        a = like(self.a, x1)
        return (1 / a - 1) * x1 + _u(u, x1) / a
