"""An inductor graph pass that reads concatenated pieces where they were made.

A model written the usual way takes its state apart and puts the derivative back together:
``x1, x2 = x.unbind(-1)`` ... ``torch.stack([x1_dot, x2_dot], -1)``. Inside a compiled
Runge-Kutta step every stage then goes through a stacked (…, nx) buffer that the next stage
takes apart again. Inductor materialises every such ``cat`` in memory (interleaved, one loop
per stage, not vectorised), although each later read only needs one of the pieces.

This pass rewrites reads of a concatenation along the concatenated dimension into reads of the
piece that holds them, so the buffer is no longer needed and is removed as dead code:

* ``select(cat(ps, d), d, i)`` -> the piece holding index ``i`` (``a`` itself when that
  piece is ``unsqueeze(a, d)``), and ``select(unsqueeze(a, d), d, 0)`` -> ``a``;
* ``slice(cat(ps, d), d, start, end)`` inside one piece -> that piece or a slice of it;
* ``unbind(x, d)[i]`` -> ``select(x, d, i)`` and ``squeeze(x, d)`` of a size-1 ``d`` ->
  ``select(x, d, 0)`` (so the rules above apply to them), and selects and slices of
  ``clone(x)`` read ``x`` (a one-piece ``cat`` decomposes into a ``clone``).

Every rewrite only removes data movement (the same values, dtype and shape are read), so the
compiled function's results are unchanged. Together with a component-major state layout
(``explicit.py``) the stages of a step of a component-wise model fuse into one vectorised loop.
The pass runs on inductor's post-grad ATen graph (``post_grad_custom_pre_pass``, see
``passes``) of the compiled component-major chunk only.
"""

from __future__ import annotations

import operator

import torch

_aten = torch.ops.aten


def _is_call(node, target) -> bool:
    return isinstance(node, torch.fx.Node) and node.op == "call_function" and node.target is target


def _value(node):
    """The example value (a fake tensor) inductor recorded for ``node``, or None."""
    return node.meta.get("val") if isinstance(node, torch.fx.Node) else None


def _dim(d: int, ndim: int) -> int:
    return d + ndim if d < 0 else d


def _cat_pieces(cat_node, dim: int):
    """``[(piece, start, stop)]`` of ``cat_node`` along ``dim``, or None where it is not a
    ``cat`` along ``dim`` or a piece's rank or dtype differs from the result (legacy empty
    pieces, type promotion)."""
    if not _is_call(cat_node, _aten.cat.default):
        return None
    out = _value(cat_node)
    pieces = cat_node.args[0]
    cat_dim = cat_node.args[1] if len(cat_node.args) > 1 else cat_node.kwargs.get("dim", 0)
    if out is None or _dim(cat_dim, out.dim()) != dim:
        return None
    spans, start = [], 0
    for piece in pieces:
        val = _value(piece)
        if val is None or val.dim() != out.dim() or val.dtype != out.dtype:
            return None
        size = int(val.shape[dim])
        spans.append((piece, start, start + size))
        start += size
    return spans


def _unsqueezed_from(node, dim: int):
    """``a`` when ``node`` is ``unsqueeze(a, dim)``, else None."""
    if not _is_call(node, _aten.unsqueeze.default):
        return None
    return node.args[0] if _dim(node.args[1], _value(node).dim()) == dim else None


def _forward_select(node):
    """The node that ``select(src, d, i)`` reads, or None when no rule applies."""
    src, dim, index = node.args
    val = _value(src)
    if val is None:
        return None
    dim = _dim(dim, val.dim())
    index = index + int(val.shape[dim]) if index < 0 else index
    inner = _unsqueezed_from(src, dim)
    if inner is not None:
        return inner
    for piece, start, stop in _cat_pieces(src, dim) or ():
        if start <= index < stop:
            inner = _unsqueezed_from(piece, dim)
            if inner is not None:
                return inner
            return (_aten.select.int, (piece, dim, index - start))
    return None


def _forward_slice(node):
    """The node that ``slice(cat, d, start, end)`` reads, or None when no rule applies."""
    src = node.args[0]
    val = _value(src)
    args = list(node.args) + [None] * (5 - len(node.args))
    dim, start, end, step = args[1] if args[1] is not None else 0, args[2], args[3], args[4]
    if val is None or (step not in (None, 1)):
        return None
    dim = _dim(dim, val.dim())
    size = int(val.shape[dim])
    if not all(isinstance(v, (int, type(None))) for v in (start, end)):
        return None  # symbolic bounds: leave to inductor
    start = 0 if start is None else max(0, min(size, start + size if start < 0 else start))
    end = size if end is None else max(0, min(size, end + size if end < 0 else end))
    for piece, lo, hi in _cat_pieces(src, dim) or ():
        if lo <= start and end <= hi and start < end:
            if (start, end) == (lo, hi):
                return piece
            return (_aten.slice.Tensor, (piece, dim, start - lo, end - lo, 1))
    return None


def _squeeze_as_select(node):
    """``select(x, d, 0)`` for ``squeeze(x, d)`` of a size-1 dimension ``d``, else None."""
    src, dims = node.args[0], node.args[1]
    dims = dims if isinstance(dims, (list, tuple)) else [dims]
    val = _value(src)
    if val is None or len(dims) != 1:
        return None
    dim = _dim(dims[0], val.dim())
    if val.shape[dim] != 1:
        return None  # squeezing a longer dimension does nothing
    return (_aten.select.int, (src, dim, 0))


def _replace(graph, node, target) -> None:
    """Replace ``node`` by ``target``: an existing node or an ``(op, args)`` to insert."""
    if isinstance(target, tuple):
        op, args = target
        with graph.inserting_before(node):
            new = graph.call_function(op, args)
        new.meta = dict(node.meta)
        new.meta["val"] = op(*[_value(a) if isinstance(a, torch.fx.Node) else a for a in args])
        target = new
    node.replace_all_uses_with(target)
    graph.erase_node(node)


def forward_cat_reads(graph: torch.fx.Graph) -> int:
    """Apply the rules of the module docstring until none applies; returns the rewrites made."""
    total = 0
    changed = True
    while changed:
        changed = False
        for node in list(graph.nodes):
            target = None
            if node.kwargs:  # ATen views here take positional arguments; leave anything else
                continue
            if _is_call(node, operator.getitem) and _is_call(node.args[0], _aten.unbind.int):
                unbind = node.args[0]
                dim = unbind.args[1] if len(unbind.args) > 1 else 0
                target = (_aten.select.int, (unbind.args[0], dim, node.args[1]))
            elif (
                _is_call(node, _aten.select.int) or _is_call(node, _aten.slice.Tensor)
            ) and _is_call(node.args[0], _aten.clone.default):
                target = (node.target, (node.args[0].args[0], *node.args[1:]))
            elif _is_call(node, _aten.squeeze.dim) or _is_call(node, _aten.squeeze.dims):
                target = _squeeze_as_select(node)
            elif _is_call(node, _aten.select.int):
                target = _forward_select(node)
            elif _is_call(node, _aten.slice.Tensor):
                target = _forward_slice(node)
            if target is not None:
                _replace(graph, node, target)
                changed = True
                total += 1
        graph.eliminate_dead_code()
    return total


def reads_only_components(call, x: torch.Tensor) -> bool:
    """Whether the model ``call(x)`` ((*batch, nx) -> (*batch, nx)) works component by
    component: it only takes ``x`` apart and builds its result with ``stack``/``cat`` along the
    last dimension, so that after :func:`forward_cat_reads` no concatenation is left when the
    state comes in as components and every output component is read on its own.

    ``call`` is traced once at the ATen level with inductor's decompositions (the graph the
    pass will see); a model that cannot be traced (data-dependent control flow, ...) counts as
    not component-wise. Models that mix components in matrix products (linear layers) are not
    component-wise: they run faster on the interleaved (*batch, nx) layout.
    """
    from torch._inductor.decomposition import select_decomp_table
    from torch.fx.experimental.proxy_tensor import make_fx

    def probe(*components):
        K = call(torch.stack(components, dim=-1))
        return tuple(K[..., i] for i in range(K.shape[-1]))

    try:
        with torch.no_grad():
            traced = make_fx(probe, decomposition_table=select_decomp_table())(*x.unbind(-1))
    except Exception:  # untraceable models keep the default layout
        return False
    forward_cat_reads(traced.graph)
    return not any(
        _is_call(node, _aten.cat.default) or _is_call(node, _aten.stack.default)
        for node in traced.graph.nodes
    )
