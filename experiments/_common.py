"""Shared plumbing for experiment scripts: command line, output folder, tables, figures.

Every experiment is a script ``experiments/<name>.py`` with ``main(argv=None)``. The four
helpers below keep them uniform::

    from experiments._common import experiment_parser, output_dir, save_figure, write_table

    def main(argv=None):
        parser = experiment_parser("my_study", "What the study shows (notes Fig. 6.10).")
        parser.add_argument("--tol", type=float, default=1e-6)   # extra options are fine
        args = parser.parse_args(argv)
        out = output_dir(args, "my_study")                      # pathlib.Path, created
        rows = [{"method": "rk4", "slope": 4.01}]
        markdown = write_table(rows, out / "slopes")            # slopes.csv + slopes.md
        fig, ax = plt.subplots()
        ...
        save_figure(fig, out / "slopes.png")
        return rows

* ``--quick``: a run of a few seconds, used by the tests.
* ``--out DIR``: where results go; default ``experiments/out/<name>``.

Files that a rerun reads back (partial results of a resumable study) are written with
:func:`atomic_write_text`: a run killed mid-write leaves the previous complete file, never a
half-written one. :func:`write_table` writes that way too.

Import pyplot through this module (``from experiments._common import plt``), or call
``matplotlib.use("Agg")`` yourself before importing ``pyplot``, so that figures are written
without a display.
"""

from __future__ import annotations

import argparse
import csv
import io
import math
import os
import pathlib
import tempfile

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402

__all__ = [
    "DEFAULT_OUT_ROOT",
    "atomic_write_text",
    "experiment_parser",
    "output_dir",
    "plt",
    "save_figure",
    "write_table",
]

DEFAULT_OUT_ROOT = pathlib.Path(__file__).resolve().parent / "out"


def experiment_parser(
    name: str, description: str, default_out: pathlib.Path | None = None
) -> argparse.ArgumentParser:
    """An argument parser with the options every experiment shares.

    Args:
        name: the experiment's name (used as program name and default output folder).
        description: one paragraph shown by ``--help``.
        default_out: output folder when ``--out`` is not given, for a script whose results
            belong somewhere else than ``experiments/out/<name>`` (e.g. ``datasets/``).

    Returns:
        A parser with ``--quick`` (flag) and ``--out DIR`` (default ``default_out`` or
        ``experiments/out/<name>``); add experiment-specific options to it.
    """
    parser = argparse.ArgumentParser(prog=name, description=description)
    parser.add_argument(
        "--quick", action="store_true", help="small, fast run (seconds); used by the tests"
    )
    shown = default_out if default_out is not None else f"experiments/out/{name}"
    parser.add_argument(
        "--out",
        type=pathlib.Path,
        default=default_out,
        help=f"output folder (default: {shown})",
    )
    return parser


def output_dir(args: argparse.Namespace, name: str) -> pathlib.Path:
    """The output folder of a run (``args.out`` or ``experiments/out/<name>``), created."""
    path = pathlib.Path(args.out) if getattr(args, "out", None) else DEFAULT_OUT_ROOT / name
    path.mkdir(parents=True, exist_ok=True)
    return path


def atomic_write_text(path, text: str) -> pathlib.Path:
    """Replace ``path`` by a file holding ``text``, atomically.

    The text goes to a temporary file in the same folder (same file system), is flushed to
    disk, and then renamed over ``path`` with :func:`os.replace`, which is atomic: a reader (or
    a rerun after a crash) sees either the old complete file or the new one.
    """
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", newline="") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise
    return path


def _format_cell(value) -> str:
    if isinstance(value, bool) or value is None:
        return str(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value) or math.isinf(value):
            return str(value)
        return f"{value:.4g}"
    try:  # numpy / torch scalars
        return _format_cell(value.item())
    except (AttributeError, ValueError):
        return str(value)


def write_table(rows: list[dict], path_stem: pathlib.Path) -> str:
    """Write ``rows`` to ``<stem>.csv`` (full precision) and ``<stem>.md`` (4 digits).

    Args:
        rows: one dict per row; the columns are the union of the keys in first-seen order
            (a missing key gives an empty cell).
        path_stem: path without suffix, e.g. ``out / "slopes"``.

    Returns:
        The Markdown table as a string (also written to ``<stem>.md``).
    """
    path_stem = pathlib.Path(path_stem)
    path_stem.parent.mkdir(parents=True, exist_ok=True)
    columns: list[str] = []
    for row in rows:
        columns.extend(key for key in row if key not in columns)

    def plain(value):
        try:
            return value.item()
        except (AttributeError, ValueError):
            return value

    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=columns)
    writer.writeheader()
    for row in rows:
        writer.writerow({key: plain(row.get(key, "")) for key in columns})
    atomic_write_text(path_stem.with_suffix(".csv"), buffer.getvalue())
    lines = [
        "| " + " | ".join(columns) + " |",
        "|" + "|".join("---" for _ in columns) + "|",
    ]
    for row in rows:
        cells = [_format_cell(row[key]) if key in row else "" for key in columns]
        lines.append("| " + " | ".join(cells) + " |")
    markdown = "\n".join(lines) + "\n"
    atomic_write_text(path_stem.with_suffix(".md"), markdown)
    return markdown


def save_figure(fig, path) -> pathlib.Path:
    """Save a matplotlib figure (PNG, 150 dpi, tight bounding box) and close it."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=150, bbox_inches="tight")
    plt.close(fig)
    return path
