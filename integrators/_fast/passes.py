"""The inductor graph passes of a compiled chunk: one ``CustomGraphPass`` for every chunk.

* :func:`scale_alpha_operands` (every chunk): ``add(a, b, alpha=c)`` and ``sub(a, b,
  alpha=c)`` become ``add(a, mul(b, c))`` and ``sub(a, mul(b, c))``. Inductor (torch 2.13)
  fuses ``add(a, mm(x, y), alpha=c)`` into ``addmm(a, x, y)`` without the coefficient, so a
  model written ``torch.add(x, x @ W.T, alpha=0.5)`` (or with ``F.linear``) stepped wrongly
  when compiled; the eager check of a chunk's first call cannot see it while the product is
  zero (a zero-initialised layer). The rewrite gives the same values up to rounding.
* ``cat_forwarding.forward_cat_reads`` (component-major chunks only).
"""

from __future__ import annotations

import torch
from torch._guards import detect_fake_mode
from torch._inductor.custom_graph_pass import CustomGraphPass, get_hash_for_files

from . import cat_forwarding

_aten = torch.ops.aten
_WITH_ALPHA = (_aten.add.Tensor, _aten.sub.Tensor)


def scale_alpha_operands(graph: torch.fx.Graph) -> int:
    """Rewrite ``add``/``sub`` of two tensors with ``alpha != 1`` into a product and a plain
    ``add``/``sub``, in place; returns the number of rewrites."""
    total = 0
    for node in list(graph.nodes):
        if node.op != "call_function" or node.target not in _WITH_ALPHA:
            continue
        alpha = node.kwargs.get("alpha", 1)
        if alpha == 1 or not isinstance(node.args[1], torch.fx.Node):
            continue
        b = node.args[1]
        with graph.inserting_before(node):
            scaled = graph.call_function(_aten.mul.Tensor, (b, alpha))
        value = b.meta.get("val")
        if value is not None:  # later passes read the shape, dtype and strides of every node
            with detect_fake_mode([value]):
                scaled.meta["val"] = _aten.mul.Tensor(value, alpha)
        node.args = (node.args[0], scaled, *node.args[2:])
        node.kwargs = {k: v for k, v in node.kwargs.items() if k != "alpha"}
        total += 1
    return total


class ChunkGraphPass(CustomGraphPass):
    """The post-grad pre-pass of a compiled chunk: :func:`scale_alpha_operands`, then (with
    ``forward_cats``) ``cat_forwarding.forward_cat_reads``. Cache key: these two files and
    the flag."""

    def __init__(self, forward_cats: bool):
        self.forward_cats = forward_cats

    def __call__(self, graph: torch.fx.Graph) -> None:
        scale_alpha_operands(graph)
        if self.forward_cats:
            cat_forwarding.forward_cat_reads(graph)

    def uuid(self):
        files = get_hash_for_files((__file__, cat_forwarding.__file__))
        return (files, self.forward_cats)
