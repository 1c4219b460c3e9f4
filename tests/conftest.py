"""Shared fixtures. Global torch state (default dtype) is restored after every test."""

import pytest
import torch


@pytest.fixture
def float64_default():
    """Run a test with float64 as torch's default dtype, restoring the previous default."""
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(previous)


def _central_difference(loss, tensor: torch.Tensor, h: float = 1e-6) -> torch.Tensor:
    """d loss() / d tensor by central differences, shape of ``tensor``: each entry is moved by
    +-h in place (under no_grad) and restored, so it works for parameters and for leaf inputs
    that ``loss`` reads from its closure."""
    grad = torch.zeros_like(tensor)
    with torch.no_grad():
        flat, out = tensor.view(-1), grad.view(-1)
        for i in range(flat.numel()):
            flat[i] += h
            up = loss()
            flat[i] -= 2 * h
            down = loss()
            flat[i] += h
            out[i] = (up - down) / (2 * h)
    return grad


@pytest.fixture
def central_difference():
    """The function ``central_difference(loss, tensor, h=1e-6)`` (finite-difference truth)."""
    return _central_difference
