"""Bytes an autograd graph holds for its backward pass, measured the same way by every
benchmark that reports it (``bench_implicit``, ``bench_neural``): each distinct storage once,
however many times autograd saved a view of it (a layer's weight is saved by every stage of
every step)."""

from __future__ import annotations

import gc
import threading
import weakref

import torch

from integrators.jacobians import graph_nodes

__all__ = ["GraphMemory", "with_large_stack"]


class _Packed:
    """A tensor saved for backward, wrapped so that a weak reference to the wrapper tells
    whether the autograd graph still holds it."""

    __slots__ = ("tensor", "__weakref__")

    def __init__(self, tensor):
        self.tensor = tensor


def _unpack(packed):
    return packed.tensor


def _tensors_in(value):
    if isinstance(value, torch.Tensor):
        return [value]
    if isinstance(value, (tuple, list)):
        return [v for v in value if isinstance(v, torch.Tensor)]
    return []


def _context_tensors(output: torch.Tensor):
    """Tensors kept as attributes of custom ``autograd.Function`` nodes in the graph of
    ``output`` (such attributes bypass the saved-tensor hooks)."""
    found = []
    for node in graph_nodes(output):
        if isinstance(node, torch.autograd.function.BackwardCFunction):
            for value in vars(node).values():
                found.extend(_tensors_in(value))
    return found


class GraphMemory:
    """Bytes an autograd graph holds for its backward pass (deterministic, on any device).

    Inside ``with GraphMemory() as meter:`` every tensor autograd saves for backward (built-in
    operations and ``save_for_backward``) passes through ``saved_tensors_hooks`` and is
    recorded. ``meter.saved_bytes(loss)`` sums the sizes of the distinct storages that the
    graphs built inside the block still hold when it is called, plus tensors kept as
    attributes of custom ``autograd.Function`` contexts reachable from ``loss``
    (``integrators.newton``'s IFT node keeps ``x*`` and its arguments that way). Temporary
    graphs built and dropped during the forward pass (Jacobians by autograd inside the
    solvers) are not counted. Call it on deep graphs through :func:`with_large_stack`.
    """

    def __enter__(self):
        self._packed = []
        self._hooks = torch.autograd.graph.saved_tensors_hooks(self._pack, _unpack)
        self._hooks.__enter__()
        return self

    def __exit__(self, *exc):
        self._hooks.__exit__(*exc)

    def _pack(self, tensor):
        packed = _Packed(tensor.detach())  # no grad_fn: no cycle through a saved output
        self._packed.append(weakref.ref(packed))
        return packed

    def saved_bytes(self, output: torch.Tensor) -> int:
        gc.collect()  # graphs dropped inside reference cycles (e.g. exception tracebacks)
        tensors = [p.tensor for ref in self._packed if (p := ref()) is not None]
        tensors += _context_tensors(output)
        storages = {}
        for tensor in tensors:
            storage = tensor.untyped_storage()
            storages[(str(tensor.device), storage.data_ptr())] = storage.nbytes()
        return sum(storages.values())


def with_large_stack(fn, megabytes=1024):
    """``fn()`` run in a thread with a large C stack (the graph it builds dies there too).

    Once Python has walked an autograd graph (:func:`_context_tensors` creates a Python
    object per node), PyTorch frees that graph recursively; graphs tens of thousands of
    nodes deep (the unrolled IRK) then overflow the default 8 MB stack and crash.
    """
    result = {}

    def target():
        try:
            result["value"] = fn()
        except BaseException as exc:  # re-raised in the caller's thread
            result["error"] = exc

    previous = threading.stack_size(megabytes * 2**20)
    try:
        thread = threading.Thread(target=target)
        thread.start()
        thread.join()
    finally:
        threading.stack_size(previous)
    if "error" in result:
        raise result["error"]
    return result["value"]
