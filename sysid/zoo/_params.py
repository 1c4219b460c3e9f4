"""Helpers shared by the plants of the zoo: physical parameters as ``nn.Parameter``.

A parameter is stored in float64 (or the floating dtype of a tensor handed in) and cast to the
dtype and device of the state in ``forward``, so a float32 simulation of a float64 plant works
and gradients still flow to the stored parameter. A tensor parameter broadcasts against the
batch: ``mu`` of shape ``(256, 1)`` gives 256 plants for states of shape ``(256, n)``.
"""

import torch
from torch import nn

from integrators.errors import InputValidationError


def as_parameter(value, name: str, positive: bool = False, vector: bool = False) -> nn.Parameter:
    """Wrap a float, array or tensor as a float ``nn.Parameter`` (float64 unless a float tensor).

    ``positive``: also require every entry > 0 (masses, lengths). Checked here only: a fit
    that drives the parameter to zero or below is not stopped (see the plant's docstring).
    ``vector``: the parameter has a last axis of its own (a matrix ``A``, an end point); a
    scalar parameter (the default) has shape ``()`` or ``(*batch, 1)``, one value per plant.

    Raises:
        InputValidationError: a value that is not numeric (a string, None), a non-finite or
            non-positive entry; a scalar parameter with a
            last axis longer than 1 (``(B,)`` for ``B`` plants would broadcast against the
            state's components instead of the batch).
    """
    if isinstance(value, torch.Tensor):
        tensor = value.detach().clone()
        if not tensor.is_floating_point():
            tensor = tensor.to(torch.float64)
    else:
        try:
            tensor = torch.as_tensor(value, dtype=torch.float64)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise InputValidationError(
                f"parameter {name!r} must be a number, an array or a tensor of numbers, got "
                f"{value!r} of type {type(value).__name__}."
            ) from exc
    if tensor.is_complex() or tensor.dtype == torch.bool:
        raise InputValidationError(
            f"parameter {name!r} must be real, got dtype {tensor.dtype} ({value!r})."
        )
    if not torch.isfinite(tensor).all():
        raise InputValidationError(f"parameter {name!r} must be finite, got {value!r}")
    if positive and not bool((tensor > 0).all()):
        raise InputValidationError(f"parameter {name!r} must be > 0, got {value!r}")
    if not vector:
        per_member(tensor, f"parameter {name!r}")
    return nn.Parameter(tensor)


def like(param: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``param`` cast (differentiably) to the dtype and device of ``x``."""
    return param.to(dtype=x.dtype, device=x.device)


def per_member(param: torch.Tensor, name: str = "a per-member scalar parameter") -> torch.Tensor:
    """A scalar parameter without its trailing broadcast axis: ``(*batch, 1)`` as
    ``(*batch,)``, a 0-dim one unchanged.

    Raises:
        InputValidationError: a trailing axis longer than 1 (e.g. ``(B,)`` for ``B`` plants,
            which would otherwise give every member the first entry).
    """
    if param.dim() == 0:
        return param
    if param.shape[-1] != 1:
        raise InputValidationError(
            f"{name} has shape (*batch, 1), got {tuple(param.shape)}; give one value per "
            "plant as a column, e.g. torch.tensor([1.0, 2.0])[:, None]."
        )
    return param[..., 0]


def like_component(param: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``like(param, x)`` without its trailing broadcast axis (:func:`per_member`): a scalar
    or ``(*batch,)`` tensor that multiplies single state components ``x[..., i]``."""
    return per_member(like(param, x))


def stack_last(*params: torch.Tensor) -> torch.Tensor:
    """Scalar parameters as the entries of a last axis: ``(k,)`` when all are scalars,
    ``(*batch, k)`` when some have the per-member shape ``(*batch, 1)`` (the others are
    broadcast), e.g. the point masses ``(M, m)`` of a batch of cranes."""
    if all(p.dim() == 0 for p in params):
        return torch.stack(params)
    columns = [p if p.dim() > 0 else p.reshape(1) for p in params]
    return torch.cat(torch.broadcast_tensors(*columns), -1)


def stack_components(*components: torch.Tensor) -> torch.Tensor:
    """Components ``(*batch_i,)`` of a right-hand side stacked on a last axis after
    broadcasting them to one batch: a per-member parameter ``(*batch, 1)`` batches the
    components it enters beyond a state shared by the members."""
    return torch.stack(torch.broadcast_tensors(*components), -1)


def cat_columns(*columns: torch.Tensor) -> torch.Tensor:
    """Columns ``(*batch_i, k_i)`` joined on the last axis after broadcasting their batches
    (see :func:`stack_components`)."""
    batch = torch.broadcast_shapes(*(c.shape[:-1] for c in columns))
    return torch.cat([c.expand(*batch, c.shape[-1]) for c in columns], -1)


def check_state(x: torch.Tensor, n: int, plant: str) -> None:
    """Raise InputValidationError unless ``x`` has shape ``(*batch, n)``."""
    if not isinstance(x, torch.Tensor) or x.dim() < 1 or x.shape[-1] != n:
        shape = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
        raise InputValidationError(f"{plant}: state must have shape (*batch, {n}), got {shape}")


def input_or_zero(u, x: torch.Tensor, nu: int) -> torch.Tensor:
    """The input ``u`` as a tensor like ``x`` with last dimension ``nu`` (zeros when None)."""
    if u is None:
        return x.new_zeros((*x.shape[:-1], nu))
    u = torch.as_tensor(u, dtype=x.dtype, device=x.device)
    if u.dim() == 0:
        u = u.expand(nu)
    if u.shape[-1] != nu:
        raise InputValidationError(f"input must have last dimension {nu}, got {tuple(u.shape)}")
    return u
