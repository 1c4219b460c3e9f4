"""Shared plumbing for experiment scripts: command line, output folder, progress, tables,
figures.

Every experiment is a script ``experiments/<name>.py`` with ``build_parser()`` and
``main(argv=None)``. The helpers below keep them uniform::

    import argparse

    from experiments._common import (
        experiment_parser, finish, output_dir, parse_early, progress, save_figure, write_table,
    )

    def build_parser() -> argparse.ArgumentParser:
        parser = experiment_parser("my_study", "What the study shows (notes Fig. 6.10).")
        parser.add_argument("--tol", type=float, default=1e-6, help="solver tolerance")
        return parser

    parse_early(__name__, build_parser)

    import torch                                   # the heavy imports come after parse_early

    from experiments._common import plt

    def main(argv=None):
        args = build_parser().parse_args(argv)
        out = output_dir(args, "my_study")                      # pathlib.Path, created
        rows = [{"method": m, "slope": study(m)} for m in progress(METHODS, "methods")]
        markdown = write_table(rows, out / "slopes")            # slopes.csv + slopes.md
        fig, ax = plt.subplots()
        ...
        save_figure(fig, out / "slopes.png")
        finish(out, markdown)                  # summary table(s), then the folder, last
        return rows

Console convention: progress bars (:func:`progress`) or progress lines (:func:`note`), both on
stderr, for anything longer than a few seconds; the summary tables as Markdown on stdout; the
results folder on the last line (``results: <folder>``), the last two by :func:`finish`.

* ``--quick``: a run of a few seconds, used by the tests; its results go to
  ``experiments/out/<name>/quick`` so that a quick run never overwrites a full run's.
* ``--out DIR``: where results go; default ``experiments/out/<name>``
  (see :func:`default_output_dir`).
* ``--help`` lists every option with its meaning and default. It answers at once: the module
  builds its parser from light imports only, and :func:`parse_early` parses the command line
  of ``python -m experiments.<name>`` before the module imports torch, scipy, matplotlib or
  ``control`` (``tests/test_experiment_conventions.py`` checks that none of them is loaded).

Files that a rerun reads back (partial results of a resumable study) are written with
:func:`atomic_write_text`: a run killed mid-write leaves the previous complete file, never a
half-written one. :func:`write_table` writes that way too.

Import pyplot through this module (``from experiments._common import plt``, imported on first
use), or call ``matplotlib.use("Agg")`` yourself before importing ``pyplot``, so that figures
are written without a display.
"""

from __future__ import annotations

import argparse
import csv
import io
import math
import os
import pathlib
import sys
import tempfile

__all__ = [
    "DATASETS_DIR",
    "DEFAULT_OUT_ROOT",
    "atomic_write_text",
    "default_output_dir",
    "experiment_parser",
    "figure_defects",
    "finish",
    "markdown_table",
    "note",
    "output_dir",
    "parse_early",
    "progress",
    "readable_log_ticks",
    "reference_slope",
    "save_figure",
    "write_table",
]

DEFAULT_OUT_ROOT = pathlib.Path(__file__).resolve().parent / "out"
QUICK_SUBDIR = "quick"
#: The versioned data sets (read by ``experiments/_datasets.py``, written by ``make_datasets``).
DATASETS_DIR = pathlib.Path(__file__).resolve().parent.parent / "datasets"


def _pyplot():
    """``matplotlib.pyplot`` with the Agg backend (figures are written without a display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot

    return matplotlib.pyplot


def __getattr__(name: str):
    """``plt`` is imported on first use, so that ``--help`` and argument errors do not pay
    for importing matplotlib."""
    if name == "plt":
        globals()["plt"] = _pyplot()
        return globals()["plt"]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """``--help`` with each option's default appended, the description's line breaks kept;
    options whose default is ``None`` (a value that depends on ``--quick``) state their
    defaults in their own help text."""

    def _get_help_string(self, action):
        if action.default is None or action.default is False:
            return action.help
        return super()._get_help_string(action)


def default_output_dir(
    name: str, quick: bool, default_out: pathlib.Path | None = None
) -> pathlib.Path:
    """The results folder of a run without ``--out``.

    Args:
        name: the experiment's name.
        quick: whether the run is a ``--quick`` one.
        default_out: the full run's folder when it is not ``experiments/out/<name>``
            (``make_datasets`` writes ``datasets/``).

    Returns:
        ``experiments/out/<name>/quick`` for a quick run (whatever ``default_out``), so that a
        quick run never overwrites a full run's results or tracked files; otherwise
        ``default_out`` or ``experiments/out/<name>``.
    """
    if quick:
        return DEFAULT_OUT_ROOT / name / QUICK_SUBDIR
    return pathlib.Path(default_out) if default_out is not None else DEFAULT_OUT_ROOT / name


def experiment_parser(
    name: str, description: str, default_out: pathlib.Path | None = None
) -> argparse.ArgumentParser:
    """An argument parser with the options every experiment shares.

    Every option added to it should have a ``help`` text: ``--help`` appends its default.

    Args:
        name: the experiment's name (used as program name and default output folder).
        description: shown by ``--help`` (line breaks kept).
        default_out: output folder of a full run when ``--out`` is not given, for a script
            whose results belong somewhere else than ``experiments/out/<name>``.

    Returns:
        A parser with ``--quick`` (flag) and ``--out DIR`` (default: see
        :func:`default_output_dir`); add experiment-specific options to it.
    """
    parser = argparse.ArgumentParser(
        prog=f"python -m experiments.{name}",
        description=description,
        formatter_class=_HelpFormatter,
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="small, fast run (seconds), the one the tests use; "
        f"results go to experiments/out/{name}/{QUICK_SUBDIR} unless --out is given",
    )
    full = default_output_dir(name, False, default_out)
    try:
        shown = full.relative_to(DEFAULT_OUT_ROOT.parent.parent)
    except ValueError:
        shown = full
    parser.add_argument(
        "--out",
        type=pathlib.Path,
        default=None,
        metavar="DIR",
        help=f"results folder (default: {shown}, or experiments/out/{name}/{QUICK_SUBDIR} "
        "with --quick)",
    )
    return parser


def parse_early(module_name: str, build_parser) -> None:
    """Parse the command line of a script run as ``python -m experiments.<name>`` now.

    Called at the top of an experiment module, after ``build_parser`` and before the heavy
    imports: ``--help`` and a wrong option print their answer and exit before torch, scipy or
    matplotlib are imported. A module imported by a test or another experiment
    (``module_name != "__main__"``) is not affected; ``main(argv)`` parses its own ``argv``.

    Args:
        module_name: the calling module's ``__name__``.
        build_parser: function of no arguments returning the experiment's parser.
    """
    if module_name == "__main__":
        build_parser().parse_args()


def output_dir(
    args: argparse.Namespace, name: str, default_out: pathlib.Path | None = None
) -> pathlib.Path:
    """The results folder of a run, created: ``args.out`` if given, else
    :func:`default_output_dir` (``default_out`` as passed to :func:`experiment_parser`)."""
    if getattr(args, "out", None):
        path = pathlib.Path(args.out)
    else:
        path = default_output_dir(name, bool(getattr(args, "quick", False)), default_out)
    path.mkdir(parents=True, exist_ok=True)
    return path


def progress(iterable, desc: str, total: int | None = None, **options):
    """A progress bar (tqdm, on stderr) over ``iterable``, labelled ``desc``.

    The bar is shown only when stderr is a terminal (tqdm's ``disable=None``): a run whose
    stderr goes to a file, a pipe or a test's capture gets no bar.

    Args:
        iterable: what the loop runs over.
        desc: what one item is, e.g. ``"noise laws"``.
        total: number of items when ``len(iterable)`` is not defined.
        **options: further ``tqdm`` options.

    Returns:
        The wrapped iterable (yields the same items).
    """
    from tqdm.auto import tqdm

    options.setdefault("disable", None)
    return tqdm(iterable, desc=desc, total=total, dynamic_ncols=True, **options)


def study_grid(grid, default: dict, choices: dict | None = None) -> dict:
    """The grid of a declared study: ``default`` where ``grid`` is None, else ``grid``, whose
    factors must be those of ``default`` (the ones the study's ``simulate`` reads: an unknown
    factor would label rows with a value nothing used) and whose values of each factor in
    ``choices`` (factor -> allowed values) must be among them.

    Raises:
        InputValidationError: a missing or unknown factor, or a value not allowed; the
            message lists what is.
    """
    from sysid.errors import InputValidationError

    if grid is None:
        return {factor: list(values) for factor, values in default.items()}
    if not isinstance(grid, dict):
        raise InputValidationError(
            f"grid must be a table of factor -> list of values with the factors {list(default)}, "
            f"got {grid!r}."
        )
    unknown, missing = sorted(set(grid) - set(default)), sorted(set(default) - set(grid))
    if unknown or missing:
        raise InputValidationError(
            f"this study's grid has the factors {list(default)} (the ones its data generator "
            f"reads); got unknown {unknown} and missing {missing}."
        )
    grid = {
        factor: list(values) if isinstance(values, (list, tuple)) else [values]
        for factor, values in grid.items()
    }
    for factor, allowed in (choices or {}).items():
        wrong = [value for value in grid[factor] if value not in allowed]
        if wrong:
            raise InputValidationError(
                f"grid factor {factor!r} takes values among {list(allowed)}; got {wrong}."
            )
    return grid


def note(message: str) -> None:
    """One progress line on stderr, for a stage that is a single batched call (no loop to
    put a progress bar on)."""
    print(message, file=sys.stderr, flush=True)


def finish(out: pathlib.Path, *tables: str) -> pathlib.Path:
    """End a run: print the summary tables (Markdown strings, e.g. from :func:`write_table`),
    then the results folder as the last line, ``results: <absolute folder>``.

    Returns:
        ``out``.
    """
    for table in tables:
        print(table.rstrip("\n") + "\n")
    print(f"results: {pathlib.Path(out).resolve()}")
    return out


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


def _columns(rows: list[dict]) -> list[str]:
    columns: list[str] = []
    for row in rows:
        columns.extend(key for key in row if key not in columns)
    return columns


def markdown_table(rows: list[dict]) -> str:
    """``rows`` as a Markdown table (numbers to 4 significant digits).

    Args:
        rows: one dict per row; the columns are the union of the keys in first-seen order
            (a missing key gives an empty cell).
    """
    columns = _columns(rows)
    lines = [
        "| " + " | ".join(columns) + " |",
        "|" + "|".join("---" for _ in columns) + "|",
    ]
    for row in rows:
        cells = [_format_cell(row[key]) if key in row else "" for key in columns]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


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
    columns = _columns(rows)

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
    markdown = markdown_table(rows)
    atomic_write_text(path_stem.with_suffix(".md"), markdown)
    return markdown


def save_figure(fig, path) -> pathlib.Path:
    """Save a matplotlib figure (PNG, 150 dpi, tight bounding box) and close it."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=150, bbox_inches="tight")
    _pyplot().close(fig)
    return path


def reference_slope(ax, dts, errors, order: float, floor: float = 0.0, **style):
    """Draw the reference line ``C dt^order`` on the log-log axes ``ax``, through the point of
    the curve ``(dts, errors)`` with the smallest ``dt`` whose error is above ``floor`` (the
    one closest to the asymptotic range, clear of round-off), over the curve's range of ``dt``;
    a curve of that order runs parallel to it.

    Args:
        ax: matplotlib axes with log scales.
        dts, errors: the measured curve (sequences of floats).
        order: the slope ``p`` of the line.
        floor: errors at or below it (round-off) are skipped.
        **style: matplotlib line options (default a dotted line).

    Returns:
        The line (``matplotlib.lines.Line2D``), or ``None`` when no error is above ``floor``.
    """
    floor = max(floor, 0.0)
    points = [(d, e) for d, e in zip(dts, errors, strict=True) if e > floor and math.isfinite(e)]
    if not points:
        return None
    dt0, err0 = min(points)
    span = [min(d for d, _ in points), max(d for d, _ in points)]
    style.setdefault("ls", ":")
    (line,) = ax.plot(span, [err0 * (d / dt0) ** order for d in span], **style)
    return line


def readable_log_ticks(axis) -> None:
    """Label a log-scaled ``axis`` (``ax.xaxis`` or ``ax.yaxis``) at 1, 2 and 5 times the powers
    of ten, written as plain numbers (``0.2``, ``500``, ``1e+04``), with unlabelled minor
    ticks: over one or two decades matplotlib's default labels every minor tick as
    ``2 x 10^-1`` and the labels overlap."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    axis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
    axis.set_minor_formatter(NullFormatter())


def figure_defects(fig) -> list[str]:
    """What makes a figure hard to read, as sentences (empty list: none found).

    Checks every axes that shows data (lines, collections, patches or images):

    * it has an x-label, or an axes below it in the same grid column has one; it has a
      y-label, or an axes left of it in the same grid row has one;
    * every line with data has a finite value;
    * no bar (rectangle patch) stands on a log-scaled value axis (a bar's length means
      nothing there);
    * a legend, if any, has no empty or repeated entry;
    * no two of the figure's axis labels, titles and tick labels overlap once drawn.

    Args:
        fig: a ``matplotlib.figure.Figure``, open or closed (drawn here on an Agg canvas).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.patches import Rectangle

    canvas = FigureCanvasAgg(fig)  # a closed figure has lost its pyplot canvas
    canvas.draw()
    renderer = canvas.get_renderer()
    problems = []
    shown = [
        ax
        for ax in fig.axes
        if ax.get_visible()
        and ax.axison
        and (ax.lines or ax.collections or ax.patches or ax.images)
    ]

    def place(ax):
        spec = ax.get_subplotspec()
        return (spec.rowspan.start, spec.colspan.start) if spec is not None else (0, 0)

    texts = []
    for ax in shown:
        row, col = place(ax)
        name = ax.get_title() or f"axes at row {row}, column {col}"
        same_col = [o for o in shown if place(o)[1] == col and place(o)[0] >= row]
        same_row = [o for o in shown if place(o)[0] == row and place(o)[1] <= col]
        if not any(o.get_xlabel() for o in same_col):
            problems.append(f"{name}: no x-label")
        if not any(o.get_ylabel() for o in same_row):
            problems.append(f"{name}: no y-label")
        for line in ax.lines:
            x, y = (list(map(float, v)) for v in line.get_data())
            if y and not any(math.isfinite(v) for v in y):
                problems.append(f"{name}: line {line.get_label()!r} has no finite value")
        bars = [p for p in ax.patches if isinstance(p, Rectangle)]
        if bars and "log" in (ax.get_xscale(), ax.get_yscale()):
            problems.append(f"{name}: {len(bars)} bars on a log axis")
        legend = ax.get_legend()
        if legend is not None:
            entries = [t.get_text() for t in legend.get_texts()]
            if any(not e.strip() for e in entries) or len(set(entries)) != len(entries):
                problems.append(f"{name}: legend entries {entries} empty or repeated")
        labels = [ax.title, ax.xaxis.label, ax.yaxis.label]
        labels += _drawn_tick_labels(ax.xaxis, 0) + _drawn_tick_labels(ax.yaxis, 1)
        texts += [(name, t) for t in labels if t.get_visible() and t.get_text().strip()]
    boxes = [(name, t.get_text(), t.get_window_extent(renderer)) for name, t in texts]
    for i, (name_a, text_a, box_a) in enumerate(boxes):
        for name_b, text_b, box_b in boxes[i + 1 :]:
            if box_a.overlaps(box_b) and _overlap_area(box_a, box_b) > 1.0:
                problems.append(f"{name_a}: {text_a!r} overlaps {name_b}: {text_b!r}")
    return problems


def _drawn_tick_labels(axis, coordinate: int) -> list:
    """The tick labels of ``axis`` (major and minor) at ticks inside its view limits (matplotlib
    keeps labels of ticks just outside, which are not drawn); ``coordinate`` is 0 for an
    x-axis, 1 for a y-axis."""
    lo, hi = sorted(axis.get_view_interval())
    slack = 1e-9 * (hi - lo)
    return [
        t
        for t in axis.get_ticklabels(which="both")
        if lo - slack <= t.get_position()[coordinate] <= hi + slack
    ]


def _overlap_area(a, b) -> float:
    """Area (pixels^2) of the intersection of two matplotlib ``Bbox``es."""
    width = min(a.x1, b.x1) - max(a.x0, b.x0)
    height = min(a.y1, b.y1) - max(a.y0, b.y0)
    return max(width, 0.0) * max(height, 0.0)
