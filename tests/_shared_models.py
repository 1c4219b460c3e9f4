"""Small right-hand sides shared by several test modules."""

import torch
from torch import nn


def pendulum(t, x, u, p):
    """Damped, forced pendulum with a time-dependent term, every argument mattering:
    theta'' = -p0 sin(theta) - p1 theta' + u + 0.1 t; state (theta, theta')."""
    return torch.stack(
        [
            x[..., 1],
            -p[..., 0] * torch.sin(x[..., 0]) - p[..., 1] * x[..., 1] + u[..., 0] + 0.1 * t,
        ],
        -1,
    )


class LinearRHS(nn.Module):
    """dx/dt = diag(a) x + b u (a, b trainable); y = x."""

    def __init__(self, a, b, method="rk4"):
        super().__init__()
        self.a = nn.Parameter(torch.as_tensor(a, dtype=torch.float64))
        self.b = nn.Parameter(torch.as_tensor(b, dtype=torch.float64))
        self.nx = self.ny = self.a.shape[0]
        self.nu, self.method, self.substeps = 1, method, 1

    def forward(self, t, x, u):
        return self.a * x + self.b * u

    def output(self, x, u):
        return x

    def physical_parameters(self):
        return {}

    def to_physical(self, name, raw):
        raise KeyError(name)
