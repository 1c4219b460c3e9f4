"""Performance machinery of the fixed-step explicit solver, kept apart from the scheme.

* :func:`compiled_stepper` (``compiled``): the entry point, a cached ``torch.compile`` of the
  solver's chunk function with its eager fallbacks;
* ``passes``: the inductor graph passes of every compiled chunk, ``cat_forwarding`` the one
  behind component-major chunks;
* ``buffers``: output buffers on huge pages and the memory still available on a device.
"""

from .buffers import available_bytes, empty_buffer
from .compiled import clear_compile_cache, compiled_stepper

__all__ = ["available_bytes", "clear_compile_cache", "compiled_stepper", "empty_buffer"]
