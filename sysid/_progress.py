"""The opt-in progress bar of long library calls (studies, fits): tqdm on stderr.

The rule: ``progress=None`` shows the bar only when stderr is a terminal, ``True`` always,
``False`` never. Library code prints nothing else.
"""

from __future__ import annotations

import sys


def progress_bar(total: int, desc: str, progress: bool | None = None, unit: str = "it"):
    """A tqdm bar over ``total`` items, labelled ``desc``, with rate and ETA.

    Args:
        total: number of items the caller will report with ``bar.update(k)``.
        desc: what one item is, e.g. ``"chunks"``.
        progress: ``None`` (on when ``sys.stderr`` is a terminal), ``True`` or ``False``.
        unit: name of one item in the rate display.

    Returns:
        A ``tqdm`` object (a disabled one when the bar is off); use it as a context manager.
    """
    from tqdm.auto import tqdm

    if progress is None:
        progress = bool(getattr(sys.stderr, "isatty", lambda: False)())
    return tqdm(total=total, desc=desc, unit=unit, disable=not progress, dynamic_ncols=True)
