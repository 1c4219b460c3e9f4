"""Large output buffers backed by transparent huge pages where the host supports them.

A fresh multi-gigabyte output (e.g. 65 536 trajectories x 1001 times x 2 states in float64
is 1 GB) is first touched while the integrator writes it, and with 4 KiB pages every 4 KiB
costs a page fault: on the CPU that is as expensive as the integration itself. Linux can
back a mapping with 2 MiB pages instead when asked (``madvise(MADV_HUGEPAGE)``, honoured in
the kernel's "always" and "madvise" THP modes), which cuts the faults 512-fold. Elsewhere
(other systems, GPU tensors, small buffers) this is a plain ``torch.empty``.
"""

from __future__ import annotations

import math
import mmap

import torch

#: Buffers of at least this many bytes are mapped with huge pages (smaller ones gain little).
HUGE_PAGE_MIN_BYTES = 64 * 2**20


def empty_buffer(shape, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """An uninitialised contiguous tensor of ``shape``, on huge pages when it is large, on
    the CPU and the host offers ``MADV_HUGEPAGE``.

    The tensor keeps its memory mapping alive (``torch.frombuffer`` holds a reference to it);
    the mapping is released with the last tensor viewing it.
    """
    device = torch.device(device)
    numel = math.prod(shape)
    nbytes = numel * torch.empty((), dtype=dtype).element_size()
    if device.type != "cpu" or nbytes < HUGE_PAGE_MIN_BYTES or not hasattr(mmap, "MADV_HUGEPAGE"):
        return torch.empty(shape, dtype=dtype, device=device)
    try:
        mapping = mmap.mmap(-1, nbytes, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
        mapping.madvise(mmap.MADV_HUGEPAGE)
    except (OSError, ValueError):  # no anonymous mappings / THP here: the ordinary allocator
        return torch.empty(shape, dtype=dtype, device=device)
    return torch.frombuffer(mapping, dtype=dtype, count=numel).view(shape)
