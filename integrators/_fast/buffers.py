"""Large output buffers backed by transparent huge pages where the host supports them, and
the memory still available on a device.

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
import os

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


def available_bytes(device) -> int | None:
    """Bytes that can still be allocated on ``device``, or None where unknown.

    CPU: ``MemAvailable`` of ``/proc/meminfo`` (free memory plus reclaimable caches), else
    the free physical pages (``os.sysconf``). CUDA: the device's free memory plus what
    PyTorch's caching allocator holds unused (``torch.cuda.mem_get_info``). Other devices:
    None.
    """
    device = torch.device(device)
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        return free + torch.cuda.memory_reserved(device) - torch.cuda.memory_allocated(device)
    if device.type != "cpu":
        return None
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024  # the file gives kB
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None
