"""Small right-hand sides shared by several test modules."""

import torch


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
