"""Read the versioned data sets of ``datasets/`` (written by ``experiments/make_datasets.py``).

Each data set is one CSV file with a header row of column names and one row per sample
(``datasets/README.md`` describes the columns and units). Library code (``integrators``,
``sysid``) never reads these files; experiments and tests do, through the two calls below::

    from experiments._datasets import load_csv, load_iodata

    ref = load_csv("vdp_reference")             # {"t": (101,), "x1": (101,), "x2": (101,)}
    data = load_iodata("msd_identification")    # sysid.IOData, u and y of shape (1000, 1)
"""

from __future__ import annotations

import pathlib

import numpy as np

from experiments._common import DATASETS_DIR
from integrators.errors import InputValidationError
from sysid import IOData

__all__ = ["DATASETS_DIR", "available", "load_csv", "load_iodata"]


def available(folder: pathlib.Path | None = None) -> list[str]:
    """Names (file stems) of the CSV data sets in ``folder`` (default ``datasets/``), sorted."""
    return sorted(p.stem for p in pathlib.Path(folder or DATASETS_DIR).glob("*.csv"))


def load_csv(name: str, folder: pathlib.Path | None = None) -> dict[str, np.ndarray]:
    """The columns of data set ``name`` as float64 arrays of shape ``(n_rows,)``.

    Args:
        name: file stem, e.g. ``"lorenz_reference"`` (a trailing ``.csv`` is accepted).
        folder: where to look (default: the repository's ``datasets/``).

    Returns:
        ``{column name: values}`` in the file's column order; values are exactly the stored
        float64 numbers (the files hold round-trip exact decimal representations).

    Raises:
        InputValidationError: no such data set (the message lists the available ones), or a
            row whose number of fields differs from the header.
    """
    folder = pathlib.Path(folder or DATASETS_DIR)
    stem = name.removesuffix(".csv")
    path = folder / f"{stem}.csv"
    if not path.is_file():
        raise InputValidationError(
            f"no data set {name!r} in {folder}; available: "
            f"{', '.join(available(folder)) or 'none'}. "
            "Regenerate missing files with `python -m experiments.make_datasets`."
        )
    with open(path) as handle:
        header = handle.readline().strip().split(",")
        try:
            values = np.loadtxt(handle, delimiter=",", dtype=np.float64, ndmin=2)
        except ValueError as err:
            raise InputValidationError(f"{path}: unreadable rows ({err}).") from err
    if values.shape[1] != len(header):
        raise InputValidationError(
            f"{path}: the header names {len(header)} columns but the rows have "
            f"{values.shape[1]} fields."
        )
    return {column: values[:, j].copy() for j, column in enumerate(header)}


def load_iodata(name: str, folder: pathlib.Path | None = None) -> IOData:
    """An identification data set (columns ``t``, ``u``, ``y``) as :class:`sysid.IOData`.

    ``Ts`` is the spacing of the uniform grid ``t`` (seconds); ``u`` and ``y`` become
    ``(N, 1)`` float64 tensors. Other columns (e.g. ``y_noise_free``) are left out: read them
    with :func:`load_csv`.

    Raises:
        InputValidationError: unknown data set, missing ``t``/``u``/``y`` columns (e.g. a
            reference trajectory), or a non-uniform time grid.
    """
    columns = load_csv(name, folder)
    missing = [c for c in ("t", "u", "y") if c not in columns]
    if missing:
        raise InputValidationError(
            f"data set {name!r} has no column(s) {missing} (it has {list(columns)}); "
            "load_iodata reads input/output data, use load_csv for trajectories."
        )
    t = columns["t"]
    if len(t) < 2:
        raise InputValidationError(f"data set {name!r} has {len(t)} sample(s); need >= 2.")
    Ts = float(t[1] - t[0])
    if not np.allclose(np.diff(t), Ts, rtol=1e-9, atol=0.0):
        raise InputValidationError(
            f"data set {name!r}: the time column is not a uniform grid (first step {Ts})."
        )
    return IOData(columns["u"], columns["y"], Ts=Ts)
