"""Jacobians of sample-wise maps by autograd.

A sample-wise map sends a batch ``x`` (*batch, n) to ``y`` (*batch, m) with output member ``i``
depending only on input member ``i`` (model right-hand sides, residuals, stage equations).
The gradient of ``sum_batch y[..., k]`` is then row ``k`` of every member's Jacobian, so ``m``
backward passes give all ``*batch`` Jacobians at once (and ``n`` forward-mode passes give
their columns). The strategies of :func:`batch_jacobian`:

* ``"vmap"``: the ``m`` backward passes as one vmapped pass (``is_grads_batched``); an operation
  without a batching rule falls back to ``"rows"``;
* ``"rows"``: ``m`` backward passes, one per output component (any differentiable map);
* ``"stacked"``: one forward and one backward pass on ``m`` stacked copies of ``x`` (the copy
  index a leading batch dimension, the unit vectors its output cotangents); the map must
  broadcast over that extra leading dimension;
* ``"forward"``: one forward-mode pass on ``n`` stacked copies of ``x`` carrying the unit
  tangents (columns instead of rows: the choice when ``m`` is much larger than ``n``, e.g.
  residuals of a long record against a few parameters); the map must broadcast over the
  copies and support forward-mode autograd.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
import torch.autograd.forward_ad as fwAD

from .errors import InputValidationError

__all__ = ["batch_jacobian", "gradients", "jacobian_rows"]

STRATEGIES = ("vmap", "rows", "stacked", "forward")


def graph_nodes(tensor: torch.Tensor) -> list:
    """The autograd nodes ``tensor`` depends on (its graph, walked depth first from
    ``grad_fn``), each once, in the order the walk meets them."""
    nodes, seen, stack = [], set(), [tensor.grad_fn]
    while stack:
        node = stack.pop()
        if node is not None and node not in seen:
            seen.add(node)
            nodes.append(node)
            stack.extend(fn for fn, _ in node.next_functions)
    return nodes


def _refuse_inference_mode(who: str) -> None:
    """Raise :class:`InputValidationError` under ``torch.inference_mode()``: it switches
    autograd off, so every derivative taken here would come out zero."""
    if torch.is_inference_mode_enabled():
        raise InputValidationError(
            f"{who}: derivatives by autograd cannot be taken under torch.inference_mode(), "
            "which switches autograd off; run under torch.no_grad() instead (it keeps "
            "autograd available to the solvers and models that differentiate inside)."
        )


def gradients(output, inputs, grad_output=None, create_graph=False):
    """``torch.autograd.grad(output, inputs, grad_output)`` with zeros for every input that
    ``output`` does not depend on, and for all of them when ``output`` has no graph (the
    derivative is then identically zero: autograd has nothing to differentiate). The graph of
    ``output`` is kept. ``inputs``: a tensor (one gradient is returned) or a sequence.
    Refused under ``torch.inference_mode()`` (:class:`InputValidationError`)."""
    _refuse_inference_mode("gradients")
    single = isinstance(inputs, torch.Tensor)
    inputs = (inputs,) if single else tuple(inputs)
    grads = (None,) * len(inputs)
    if output.requires_grad:
        grads = torch.autograd.grad(
            output,
            inputs,
            grad_output,
            create_graph=create_graph,
            retain_graph=True,
            allow_unused=True,
        )
    grads = tuple(
        torch.zeros_like(x) if g is None else g for g, x in zip(grads, inputs, strict=True)
    )
    return grads[0] if single else grads


def jacobian_rows(
    out: torch.Tensor,
    inputs: Sequence[torch.Tensor],
    create_graph: bool = False,
    batched: bool = False,
) -> list[torch.Tensor]:
    """Per-sample Jacobians ``d out / d input`` (*batch, m, n_input) of an already computed
    sample-wise ``out`` (*batch, m): the ``m`` backward passes of the module docstring, one
    per output component, or with ``batched`` as one vmapped pass (the ``"vmap"`` strategy;
    an operation without a batching rule falls back to one pass per component).

    An input ``out`` does not depend on gets zeros. ``create_graph=True`` keeps the result
    differentiable (higher derivatives); the graph of ``out`` is kept either way. Refused
    under ``torch.inference_mode()`` (:class:`InputValidationError`).
    """
    _refuse_inference_mode("jacobian_rows")
    inputs = tuple(inputs)
    m = out.shape[-1]
    if batched and out.requires_grad:
        basis = torch.eye(m, dtype=out.dtype, device=out.device)
        basis = basis.view(m, *([1] * (out.dim() - 1)), m).expand(m, *out.shape)
        try:
            grads = torch.autograd.grad(
                out,
                inputs,
                basis,
                retain_graph=True,
                create_graph=create_graph,
                allow_unused=True,
                is_grads_batched=True,
            )
        except (RuntimeError, NotImplementedError):
            pass
        else:
            return [
                x.new_zeros(*x.shape[:-1], m, x.shape[-1]) if g is None else g.movedim(0, -2)
                for g, x in zip(grads, inputs, strict=True)
            ]
    rows = [
        gradients(out[..., k].sum(), inputs, create_graph=create_graph)
        for k in range(out.shape[-1])
    ]
    return [torch.stack([r[i] for r in rows], -2) for i in range(len(inputs))]


def batch_jacobian(
    fn: Callable, x: torch.Tensor, *args, strategy: str = "vmap", outputs: int | None = None
):
    """Batched Jacobian of a sample-wise ``fn(x, *args) -> (*batch, m)`` w.r.t. ``x`` (*batch, n).

    ``strategy``: ``"vmap"``, ``"rows"``, ``"stacked"`` or ``"forward"`` (module docstring).
    ``outputs``: ``m`` where the caller knows it ("stacked" otherwise evaluates ``fn`` once
    more to learn it). An output without batch dimensions (a map that ignores ``x``'s batch)
    is broadcast to it.

    Returns:
        ``(y, J)`` detached: ``y = fn(x, *args)`` (*batch, m) and ``J`` (*batch, m, n).

    Raises:
        InputValidationError: an unknown strategy, or a call under ``torch.inference_mode()``
            (which switches autograd off: every Jacobian would come out zero).
    """
    if strategy not in STRATEGIES:
        raise InputValidationError(
            f"batch_jacobian: unknown strategy {strategy!r}; use one of {STRATEGIES}."
        )
    _refuse_inference_mode("batch_jacobian")
    batch, n = x.shape[:-1], x.shape[-1]
    with torch.enable_grad():
        if strategy == "stacked":
            return _stacked(fn, x, args, outputs)
        if strategy == "forward":
            return _forward(fn, x, args)
        xg = x.detach().requires_grad_(True)
        y = _batch_shaped(fn(xg, *args), batch)
        if not y.requires_grad:  # fn does not depend on x
            return y.detach(), y.new_zeros(*y.shape, n)
        (J,) = jacobian_rows(y, (xg,), batched=strategy == "vmap")
    return y.detach(), J.detach()


def _batch_shaped(y: torch.Tensor, batch: torch.Size) -> torch.Tensor:
    """``y`` (*batch, m), broadcast from fewer batch dimensions; a larger batch (the map mixes
    in a batch of its own, e.g. batched parameters) is refused: the members would not be
    independent. An output of x's batch shape itself (one value per member, the trailing
    ``m`` axis missing) is refused rather than read as one unbatched output of ``m`` values."""
    if y.dim() == 0 or (len(batch) > 0 and y.shape == batch):
        raise InputValidationError(
            f"batch_jacobian: fn returned shape {tuple(y.shape)} for x of batch shape "
            f"{tuple(batch)}; it must return (*batch, m): keep a trailing axis for a single "
            "output (r.unsqueeze(-1))."
        )
    try:
        return y.expand(*batch, y.shape[-1])
    except RuntimeError:
        raise InputValidationError(
            f"batch_jacobian: fn returned shape {tuple(y.shape)} for x of batch shape "
            f"{tuple(batch)}; the output's batch dimensions must be x's (expand x to the "
            "batch of the map's parameters first)."
        ) from None


def _stacked(fn, x, args, m):
    """``batch_jacobian`` by one forward and one backward pass on ``m`` stacked copies of ``x``."""
    batch, n = x.shape[:-1], x.shape[-1]
    if m is None:
        m = fn(x.detach(), *args).shape[-1]
    xg = x.detach().expand(m, *batch, n).requires_grad_(True)
    ys = _batch_shaped(fn(xg, *args), torch.Size((m, *batch)))
    if not ys.requires_grad:
        return ys[0].detach(), x.new_zeros(*batch, m, n)
    basis = torch.eye(m, dtype=ys.dtype, device=ys.device).reshape(m, *([1] * len(batch)), m)
    (g,) = torch.autograd.grad(ys, xg, basis.expand(m, *batch, m), allow_unused=True)
    J = x.new_zeros(*batch, m, n) if g is None else g.movedim(0, -2)
    return ys[0].detach(), J.detach()


def _forward(fn, x, args):
    """``batch_jacobian`` by one forward-mode pass on ``n`` stacked copies of ``x`` whose
    tangents are the unit vectors (copy ``j`` carries column ``j``)."""
    batch, n = x.shape[:-1], x.shape[-1]
    eye = torch.eye(n, dtype=x.dtype, device=x.device)
    # materialised: forward-mode duals of broadcast views (stride 0) are not supported
    tangent = eye.reshape(n, *([1] * len(batch)), n).expand(n, *x.shape).clone()
    primal = x.detach().expand(n, *x.shape).clone()
    with fwAD.dual_level():
        y, columns = fwAD.unpack_dual(fn(fwAD.make_dual(primal, tangent), *args))
    y = _batch_shaped(y, torch.Size((n, *batch)))
    J = torch.zeros_like(y) if columns is None else columns.expand_as(y)
    return y[0].detach(), J.movedim(0, -1).detach()
