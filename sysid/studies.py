"""Declared Monte-Carlo studies: batched, resumable, reproducible, spread over Dask workers.

A study is declared once::

    study = Study(simulate, {"fir_ls": lambda d: fit(FIR(3, 1), d)},
                  grid={"N": [100, 400]}, trials=6000, seed=11, chunk=500,
                  truth={"b1": 1.0, "b2": 0.5, "b3": 0.2})
    study.run("out/fir")            # resumable: finished chunks are kept
    study.summary()                 # bias, std, RMSE, mean SE, coverage per parameter
    study.report("out/fir/report")  # Markdown tables and figures

and runs every grid point's ``trials`` data sets in chunks of ``chunk`` trials, one batched
estimator call per chunk and estimator.

Seeding. Trials are grouped in fixed blocks of ``block`` trials (``chunk`` is a multiple of
``block``); block ``b`` of grid point ``i`` draws its data from a ``torch.Generator`` seeded by
``numpy.random.SeedSequence(seed, spawn_key=(i, b))``, with ``simulate(point, n, generator)``
called once per block (with ``n = block``, also for a last block that holds fewer trials: the
trials past ``trials`` are drawn and dropped). A trial's data therefore depend only on the
seed, the block size, its grid point and its index, never on the chunk size, the number of
trials or the order in which chunks run. ``block=1`` (the default) calls ``simulate`` once per
trial; a larger block draws many trials in one batched call (faster) and keeps that guarantee
for every chunk size that is a multiple of it.

Storage. ``run(out_dir)`` writes ``out_dir/manifest.json`` (the declaration and its hash) and
one Parquet file per finished chunk under ``out_dir/chunks/``, each written to a temporary
file and renamed into place (:func:`os.replace`, atomic), so an interrupted run leaves only
complete chunks and a rerun computes only the missing ones. A folder whose chunk files belong
to a different declaration (its manifest) is refused with
:class:`~sysid.errors.StudyDeclarationError`; one without chunk files takes the new one.

Results. :attr:`Study.results` is a tidy table, one row per grid point x estimator x trial x
parameter, with columns ``<factors...>, estimator, trial, parameter, estimate, se, converged,
loss, time, covariance_row, error`` (``time``: the chunk's estimator time divided by its
trials, in seconds; ``covariance_row``: the parameter's row of the reported covariance, in the
order of the parameters; ``error``: empty, or the error the estimator raised for that trial).

Failures. An estimator that raises one of the project's errors
(:class:`~sysid.errors.RKIdentError`, e.g. a :class:`~sysid.errors.ConvergenceError` for a
batch) on a chunk is called again on each half of it, down to single trials, so the trials
that make it fail are found: their rows hold NaN, ``converged`` False and the error's message,
the other trials their estimates, whatever the chunk size (the rows of a chunk it fails for
entirely take the parameter names of the other chunks). Where it fails for every trial of the
study the error is raised (a mistake in the declaration, not a property of some data sets).
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import math
import os
import pathlib
import tempfile
import time
import warnings
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

from .data import IOData
from .errors import InputValidationError, RKIdentError, RKIdentWarning, StudyDeclarationError
from .montecarlo import summarize_estimates

__all__ = ["WORKER_ENVIRONMENT", "Study", "local_cluster"]

FORMAT_VERSION = 1
RESERVED_COLUMNS = (
    "estimator",
    "trial",
    "parameter",
    "estimate",
    "se",
    "converged",
    "loss",
    "time",
    "covariance_row",
    "error",
    # columns of the summaries (and their intermediate ones)
    "truth",
    "usable",
    "error2",
    "inside",
    "trials",
    "estimated",
    "mean",
    "bias",
    "bias_se",
    "std",
    "mse",
    "rmse",
    "mean_se",
    "se_over_std",
    "coverage",
    "rel_frobenius_reported",
    "rel_frobenius_theory",
    "rel_frobenius_reported_vs_theory",
    "points",
    "bias_slope",
    "std_slope",
    "rmse_slope",
    "z",
    "ks_statistic",
    "ks_pvalue",
)


#: Environment of dask worker processes that run study chunks, set before they start
#: (``distributed.nanny.pre-spawn-environ``; :func:`local_cluster` does it). Dask's default
#: ``MALLOC_TRIM_THRESHOLD_=65536`` makes glibc hand freed memory back at once and allocate
#: every block above 128 kB by a fresh ``mmap``; torch's CPU tensors come from malloc, so
#: each operation on a large tensor faults its pages in anew, and a chunk takes nearly
#: twice the CPU time it takes in this process. A high trim threshold and an ``mmap``
#: threshold of 32 MiB keep freed blocks for reuse.
WORKER_ENVIRONMENT = {"MALLOC_TRIM_THRESHOLD_": 2**40, "MALLOC_MMAP_THRESHOLD_": 2**25}


def local_cluster(workers: int, **kwargs):
    """A ``dask.distributed.LocalCluster`` of ``workers`` one-thread worker processes
    started with :data:`WORKER_ENVIRONMENT`, for ``Study.run(client=Client(cluster))``;
    ``kwargs`` go to ``LocalCluster`` (e.g. ``memory_limit``). Use it as a context manager.

    Raises:
        ImportError: ``dask.distributed`` is not installed (``pip install 'rkident[dask]'``).
    """
    try:
        import dask
        from dask.distributed import LocalCluster
    except ImportError as err:
        raise ImportError(
            "local_cluster needs dask.distributed: pip install 'rkident[dask]'."
        ) from err
    options = dict(threads_per_worker=1, processes=True, dashboard_address=None)
    options.update(kwargs)
    with dask.config.set({"distributed.nanny.pre-spawn-environ": WORKER_ENVIRONMENT}):
        return LocalCluster(n_workers=workers, **options)


def _pandas():
    import pandas

    return pandas


def _plain(value, where: str):
    """A grid value as a JSON scalar (int, float, str, bool), or an error naming it."""
    if hasattr(value, "item") and not isinstance(value, (str, bytes)):
        value = value.item()
    if isinstance(value, (bool, int, float, str)):
        return value
    raise InputValidationError(
        f"{where} is {value!r} ({type(value).__name__}); grid values must be numbers, strings "
        "or booleans (they are stored in the study's manifest and results table)."
    )


def _block_generator(seed: int, point: int, block: int) -> torch.Generator:
    """The generator of block ``block`` of grid point ``point``: seeded from the master seed
    and the block's coordinates only."""
    state = np.random.SeedSequence(seed, spawn_key=(point, block)).generate_state(1, np.uint64)
    return torch.Generator().manual_seed(int(state[0]))


def _atomic_write_parquet(frame, path: pathlib.Path) -> None:
    """Write ``frame`` to ``path`` through a temporary file in the same folder and
    :func:`os.replace` (a reader sees the old file or the complete new one)."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        frame.to_parquet(tmp, index=False)
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


def _atomic_write_text(path: pathlib.Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as handle:
            handle.write(text)
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


def _markdown(frame) -> str:
    """``frame`` as a Markdown table, numbers to 4 significant digits."""

    def cell(value) -> str:
        if isinstance(value, float):
            return f"{value:.4g}"
        return str(value)

    columns = list(frame.columns)
    lines = ["| " + " | ".join(columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
    for row in frame.itertuples(index=False):
        lines.append("| " + " | ".join(cell(v) for v in row) + " |")
    return "\n".join(lines) + "\n"


class Study:
    """A declared Monte-Carlo study of estimators over a grid of factors.

    Args:
        simulate: ``simulate(point, n, generator) -> IOData``: ``n`` data sets (batch shape
            ``(n,)``) of grid point ``point`` (a dict factor -> value), all randomness drawn
            from ``generator``.
        estimators: name -> callable ``IOData -> FitResult`` (anything :func:`sysid.fit`
            returns: ``theta`` ``(n, p)``, ``standard_errors``, ``covariance`` ``(n, p, p)``,
            ``converged`` ``(n,)``, ``loss_history`` ``(iterations + 1, n)``,
            ``parameter_names``), called once per chunk with the chunk's trials as a batch.
        grid: factor name -> list of values (numbers, strings, booleans); the study runs every
            combination (the first factor varies slowest). Default: one point, no factors.
        trials: data sets per grid point (>= 2).
        seed: master seed (>= 0).
        chunk: trials per batched estimator call and per checkpoint file.
        block: trials per ``simulate`` call and per derived generator; ``chunk`` must be a
            multiple of it (see the module docstring: results do not depend on ``chunk``).
        truth: true parameter values by name, a dict or ``truth(point) -> dict`` (for bias,
            RMSE and coverage; parameters it does not name get NaN there).
        theory: ``theory(point, estimator_name) -> (p, p)`` covariance or None: the
            theoretical covariance where a closed form exists (e.g. ``sigma^2 (U'U)^-1`` of
            FIR least squares with a fixed input, the course notes (Modelling and
            Simulation) eq. 4.101).
        version: a label of the study's code (simulate, estimators); changing it refuses
            results computed by another version in the same folder.

    Raises:
        InputValidationError: an argument of the wrong kind or out of range.
    """

    def __init__(
        self,
        simulate: Callable[[dict, int, torch.Generator], IOData],
        estimators: Mapping[str, Callable[[IOData], object]],
        grid: Mapping[str, list] | None = None,
        trials: int = 1000,
        seed: int = 0,
        chunk: int = 500,
        *,
        block: int = 1,
        truth: Mapping[str, float] | Callable[[dict], Mapping[str, float]] | None = None,
        theory: Callable[[dict, str], object] | None = None,
        version: str = "",
    ):
        if not callable(simulate):
            raise InputValidationError("simulate must be a callable (point, n, generator).")
        if not isinstance(estimators, Mapping) or not estimators:
            raise InputValidationError("estimators must be a non-empty dict name -> callable.")
        for name, estimator in estimators.items():
            if not isinstance(name, str) or not callable(estimator):
                raise InputValidationError(
                    f"estimator {name!r} must be a string name mapped to a callable "
                    "IOData -> FitResult."
                )
        grid = {} if grid is None else dict(grid)
        clean = {}
        for factor, values in grid.items():
            if not isinstance(factor, str) or factor in RESERVED_COLUMNS:
                raise InputValidationError(
                    f"grid factor {factor!r} must be a string other than the column names "
                    f"of the results and summaries {RESERVED_COLUMNS}."
                )
            values = list(values) if isinstance(values, (list, tuple, np.ndarray)) else [values]
            if not values:
                raise InputValidationError(f"grid factor {factor!r} has no values.")
            clean[factor] = [_plain(v, f"grid[{factor!r}][{i}]") for i, v in enumerate(values)]
            repeated = sorted({repr(v) for v in clean[factor] if clean[factor].count(v) > 1})
            if repeated:
                raise InputValidationError(
                    f"grid factor {factor!r} repeats the values {', '.join(repeated)}; give each "
                    "value once (more trials come from trials=)."
                )
        for label, value, low in (
            ("trials", trials, 2),
            ("seed", seed, 0),
            ("chunk", chunk, 1),
            ("block", block, 1),
        ):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
                raise InputValidationError(f"{label} must be an integer >= {low}, got {value!r}.")
        if chunk % block:
            raise InputValidationError(
                f"chunk = {chunk} is not a multiple of block = {block}; choose a chunk that is, "
                "so that every chunk holds whole blocks."
            )
        self.simulate = simulate
        self.estimators = dict(estimators)
        self.grid = clean
        self.trials, self.seed = int(trials), int(seed)
        self.chunk, self.block = int(chunk), int(block)
        self.truth = truth
        self.theory = theory
        self.version = str(version)
        self.points: list[dict] = [
            dict(zip(clean, combo, strict=True)) for combo in itertools.product(*clean.values())
        ]
        self._results = None

    # ------------------------------------------------------------------ declaration
    @property
    def declaration(self) -> dict:
        """What identifies the study's results: grid, the order of its factors (it numbers the
        grid points, and so their seeds and chunk files), trials, seed, chunk, block,
        estimator names, version (stored in ``manifest.json``)."""
        return {
            "format": FORMAT_VERSION,
            "grid": self.grid,
            "factors": list(self.grid),
            "trials": self.trials,
            "seed": self.seed,
            "chunk": self.chunk,
            "block": self.block,
            "estimators": list(self.estimators),
            "version": self.version,
        }

    @property
    def declaration_hash(self) -> str:
        text = json.dumps(self.declaration, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()

    @property
    def n_chunks(self) -> int:
        """Chunks per grid point."""
        return math.ceil(self.trials / self.chunk)

    def _check_manifest(self, folder: pathlib.Path) -> None:
        """Write the manifest into a folder that holds no results (new, or left by a run that
        failed before its first chunk), or refuse a folder of another declaration."""
        path = folder / "manifest.json"
        mine = {"declaration": self.declaration, "hash": self.declaration_hash}
        has_chunks = (folder / "chunks").exists() and any((folder / "chunks").glob("*.parquet"))
        if not has_chunks or not path.exists():
            if has_chunks:
                raise StudyDeclarationError(
                    f"{folder} holds chunk files but no manifest.json, so their declaration is "
                    "unknown; run the study in a new folder or delete that one."
                )
            _atomic_write_text(path, json.dumps(mine, indent=2, sort_keys=True) + "\n")
            return
        try:
            stored = json.loads(path.read_text())
            theirs = stored["declaration"]
        except (ValueError, KeyError, TypeError) as err:
            raise StudyDeclarationError(
                f"{path} cannot be read ({err}); the folder's declaration is unknown: run the "
                "study in a new folder or delete that one."
            ) from err
        if stored.get("hash") != self.declaration_hash or theirs != self.declaration:
            changed = sorted(  # as the hash compares them: their JSON text
                key
                for key in set(theirs) | set(self.declaration)
                if json.dumps(theirs.get(key), sort_keys=True)
                != json.dumps(self.declaration.get(key), sort_keys=True)
            )
            details = "; ".join(
                f"{key}: stored {json.dumps(theirs.get(key), sort_keys=True)}, now "
                f"{json.dumps(self.declaration.get(key), sort_keys=True)}"
                for key in changed
            )
            raise StudyDeclarationError(
                f"{folder} holds results of a different study declaration ({details}). Results "
                "of different declarations are never mixed: run this study in a new folder, "
                "delete the old one, or restore the stored declaration."
            )

    # ------------------------------------------------------------------ one chunk
    def _chunk_path(self, folder: pathlib.Path, point: int, chunk: int) -> pathlib.Path:
        return folder / "chunks" / f"point{point:04d}-chunk{chunk:06d}.parquet"

    def _chunk_trials(self, chunk: int) -> range:
        return range(chunk * self.chunk, min((chunk + 1) * self.chunk, self.trials))

    def data(self, point: int = 0, chunk: int = 0) -> IOData:
        """The data sets the study fits in chunk ``chunk`` of grid point ``point`` (trials
        ``chunk * self.chunk`` up to the next chunk's first), drawn from the study's seed as
        :meth:`run` draws them; batch shape ``(n,)``, one ``simulate`` call of ``block`` data
        sets per block (a last block's extra ones dropped).

        Raises:
            InputValidationError: ``point`` or ``chunk`` out of range, or ``simulate``
                returned something else than an IOData of batch shape ``(n,)``.
        """
        if not (0 <= point < len(self.points) and 0 <= chunk < self.n_chunks):
            raise InputValidationError(
                f"the study has grid points 0..{len(self.points) - 1} and chunks "
                f"0..{self.n_chunks - 1}; got point={point}, chunk={chunk}."
            )
        trials = self._chunk_trials(chunk)
        parts = []
        n = self.block
        for start in range(trials.start, trials.stop, n):
            generator = _block_generator(self.seed, point, start // n)
            data = self.simulate(dict(self.points[point]), n, generator)
            if not isinstance(data, IOData) or tuple(data.batch_shape) != (n,):
                raise InputValidationError(
                    f"simulate(point={self.points[point]}, n={n}, generator) returned "
                    f"{data!r}; it must return an IOData of batch shape ({n},)."
                )
            parts.append(data if start + n <= trials.stop else data[: trials.stop - start])
        return parts[0] if len(parts) == 1 else IOData.cat(parts)

    def _compute_chunk(self, point: int, chunk: int, names: dict | None = None):
        """The results rows of one chunk (all estimators), as a DataFrame. ``names``: estimator
        -> its parameter names, for the rows of an estimator that fails for every trial of the
        chunk (raises :class:`_NamesUnknown` where they are not known yet, the error itself
        where they never can be: every trial of the study failed)."""
        pd = _pandas()
        data = self.data(point, chunk)
        trials = np.asarray(self._chunk_trials(chunk))
        frames = []
        for name, estimator in self.estimators.items():
            start = time.perf_counter()
            parts = _fit_or_split(estimator, data, 0, len(trials))
            elapsed = time.perf_counter() - start
            results = [r for _, _, r, error in parts if error is None]
            for result in results:
                _check_result(name, result)
            if results:
                estimator_names = list(results[0].parameter_names)
            elif names is None:  # every trial of the chunk failed: names from other chunks
                raise _NamesUnknown(parts[0][3])
            elif name not in names:  # every trial failed: not a property of some data sets
                raise parts[0][3]
            else:
                estimator_names = names[name]
            seconds = elapsed / len(trials)
            for lo, hi, result, error in parts:
                frames.append(_rows(name, estimator_names, trials[lo:hi], result, error, seconds))
        out = pd.concat(frames, ignore_index=True)
        for position, (factor, value) in enumerate(self.points[point].items()):
            out.insert(position, factor, value)
        return out

    def _read_chunk(self, path: pathlib.Path, chunk: int):
        """A finished chunk's rows, or None (with a warning) when its file is unreadable or
        does not hold the chunk's trials of every estimator."""
        pd = _pandas()
        try:
            frame = pd.read_parquet(path)
            expected = set(self._chunk_trials(chunk))
            ok = set(frame["estimator"]) == set(self.estimators) and all(
                set(group["trial"]) == expected for _, group in frame.groupby("estimator")
            )
        except Exception as err:  # any unreadable file (truncated, not Parquet, ...)
            reason = f"{type(err).__name__}: {err}"
        else:
            if ok:  # files written before the error column: no trial failed
                return frame if "error" in frame else frame.assign(error="")
            reason = "it does not hold this chunk's trials of every estimator"
        warnings.warn(
            f"chunk file {path} cannot be used ({reason}); recomputing that chunk.",
            RKIdentWarning,
            stacklevel=3,
        )
        return None

    # ------------------------------------------------------------------ running
    def run(self, out_dir=None, client=None, progress: bool | None = None) -> Study:
        """Run (or resume) the study in ``out_dir``.

        Args:
            out_dir: the study's folder (created): ``manifest.json`` and ``chunks/*.parquet``.
                None runs it in memory: nothing written, nothing to resume from.
            client: a ``dask.distributed.Client``: each missing chunk becomes one task on its
                workers, whose rows come back to this process to be written. None: chunks
                run here, one after the other. Start the workers with
                :data:`WORKER_ENVIRONMENT` (:func:`local_cluster` on one machine), or
                each chunk may take nearly twice the time.
            progress: progress bar over chunks (tqdm, with ETA): None shows it when stderr is
                a terminal, True always, False never.

        Returns:
            ``self``, with :attr:`results` loaded.

        Raises:
            StudyDeclarationError: ``out_dir`` holds results of another declaration.
            ImportError: ``client`` given but ``dask.distributed`` is not installed.
            Whatever ``simulate`` or an estimator raises: the chunks finished before it are
            kept, and a rerun starts from them.
        """
        from ._progress import progress_bar

        folder = None if out_dir is None else pathlib.Path(out_dir)
        coordinates = [(i, c) for i in range(len(self.points)) for c in range(self.n_chunks)]
        done = {}
        if folder is not None:
            (folder / "chunks").mkdir(parents=True, exist_ok=True)
            self._check_manifest(folder)
            for i, c in coordinates:
                path = self._chunk_path(folder, i, c)
                if path.exists():
                    frame = self._read_chunk(path, c)
                    if frame is not None:
                        done[i, c] = frame
        pending = [key for key in coordinates if key not in done]
        # chunk files are written by one background thread while the next chunk computes
        # (Parquet encoding and file I/O release the GIL); every write is waited for before
        # run returns or raises, so a finished chunk is on disk unless the process dies
        writer = ThreadPoolExecutor(max_workers=1) if folder is not None else None
        writes = []

        def finish(key, frame):
            if writer is not None:
                path = self._chunk_path(folder, *key)
                writes.append(writer.submit(_atomic_write_parquet, frame, path))
            done[key] = frame

        try:
            with progress_bar(len(coordinates), "study chunks", progress, unit="chunk") as bar:
                bar.update(len(done))
                deferred = []  # chunks an estimator failed for entirely before its names were known
                if client is None:
                    for key in pending:
                        try:
                            finish(key, self._compute_chunk(*key))
                            bar.update(1)
                        except _NamesUnknown:
                            deferred.append(key)
                else:
                    deferred = self._run_dask(client, pending, finish, bar)
                for key in deferred:  # here, with the parameter names of the finished chunks
                    finish(key, self._compute_chunk(*key, names=_parameter_names(done)))
                    bar.update(1)
        finally:
            if writer is not None:
                writer.shutdown(wait=True)
        for write in writes:
            write.result()  # a failed write raises here
        self._results = _pandas().concat([done[key] for key in coordinates], ignore_index=True)
        return self

    def _run_dask(self, client, pending, finish, bar) -> None:
        try:
            from dask.distributed import as_completed
        except ImportError as err:
            raise ImportError(
                "Study.run(client=...) needs dask.distributed: pip install 'rkident[dask]' "
                "(or run without a client, in this process)."
            ) from err
        # the declaration alone travels with each task, not the results of an earlier run
        task = copy.copy(self)
        task._results = None
        futures = {client.submit(task._compute_chunk, *key, pure=False): key for key in pending}
        deferred = []
        try:
            for future in as_completed(futures):
                try:
                    finish(futures[future], future.result())
                    bar.update(1)
                except _NamesUnknown:
                    deferred.append(futures[future])
        finally:
            client.cancel(list(futures))
        return deferred

    # ------------------------------------------------------------------ results
    @property
    def results(self):
        """The tidy results table (pandas DataFrame; see the module docstring)."""
        if self._results is None:
            raise InputValidationError(
                "the study has no results yet: call study.run(out_dir) first (it loads "
                "finished chunks and computes the missing ones)."
            )
        return self._results

    @property
    def factors(self) -> list[str]:
        return list(self.grid)

    def _truth_table(self):
        """Rows factor values..., parameter, truth (empty when no truth was declared); warns
        about a declared truth that names no estimator's parameter (a misspelt name would
        otherwise leave NaN in the bias of the parameter it meant)."""
        pd = _pandas()
        rows = []
        for point in self.points:
            values = self.truth(dict(point)) if callable(self.truth) else (self.truth or {})
            for parameter, value in dict(values).items():
                try:
                    value = float(value)
                except (TypeError, ValueError) as err:
                    raise InputValidationError(
                        f"truth[{parameter!r}] = {value!r} at grid point {point} is not a number."
                    ) from err
                rows.append({**point, "parameter": parameter, "truth": value})
        table = pd.DataFrame(rows, columns=[*self.factors, "parameter", "truth"])
        table["truth"] = table["truth"].astype(float)  # also when empty (no truth declared)
        known = set(self.results["parameter"])
        unknown = sorted(set(table["parameter"]) - known)
        if unknown:
            warnings.warn(
                f"the study's truth names {unknown}, which no estimator has (their parameters "
                f"are {sorted(known)}); check the spelling: a parameter without a truth gets "
                "NaN bias, RMSE and coverage.",
                RKIdentWarning,
                stacklevel=3,
            )
        return table

    def _usable(self, converged_only: bool):
        """The results with a boolean column ``usable``: the rows whose estimate enters the
        statistics, the one rule of every summary: a finite estimate whose standard error is
        not ``+inf`` (a parameter the data set does not determine, e.g. the input
        coefficients of a data set with a zero input: its estimate is arbitrary) and, with
        ``converged_only``, a converged fit."""
        frame = self.results
        usable = np.isfinite(frame["estimate"]) & ~np.isposinf(frame["se"])
        if converged_only:
            usable &= frame["converged"].astype(bool)
        return frame.assign(usable=usable)

    def summary(self, level: float = 0.95, converged_only: bool = False):
        """Statistics per grid point x estimator x parameter.

        Columns: the factors, ``estimator``, ``parameter``, ``trials``, ``estimated`` (trials
        with a finite estimate), ``truth``, ``mean``, ``bias`` (mean - truth), ``bias_se``
        (std / sqrt(estimated): is the bias significant?), ``std`` (sample standard
        deviation), ``rmse`` (sqrt of the mean squared error), ``mean_se`` (mean reported
        standard error), ``se_over_std``, ``coverage`` (fraction of trials with
        ``|estimate - truth| <= z se``, ``z`` the normal quantile of ``level``),
        ``converged`` (fraction of all trials). Without truth: NaN in bias, rmse, coverage.

        Only usable estimates enter the statistics: a trial whose estimate is not finite (a
        failed fit) or whose standard error is ``+inf`` (the data set does not determine the
        parameter), and with ``converged_only`` one whose fit did not converge, counts in
        ``trials`` and ``converged`` only (``estimated`` counts the others); ``mean_se``
        and ``coverage`` take the usable trials with a finite standard error. The same rule
        holds in :meth:`covariances`, :meth:`normalized_errors` and the report.
        """
        from scipy.stats import norm

        pd = _pandas()
        z = float(norm.ppf(0.5 + level / 2))
        keys = [*self.factors, "estimator", "parameter"]
        frame = (
            self._usable(converged_only)
            .drop(columns="covariance_row")
            .merge(self._truth_table(), on=[*self.factors, "parameter"], how="left")
        )
        frame["estimate"] = frame["estimate"].where(frame["usable"])
        frame["se"] = frame["se"].where(frame["usable"] & np.isfinite(frame["se"]))
        frame["error2"] = (frame["estimate"] - frame["truth"]) ** 2
        frame["inside"] = ((frame["estimate"] - frame["truth"]).abs() <= z * frame["se"]).where(
            frame["truth"].notna() & frame["se"].notna()
        )
        grouped = frame.groupby(keys, sort=False)
        out = grouped.agg(
            trials=("trial", "size"),
            estimated=("estimate", "count"),
            truth=("truth", "first"),
            mean=("estimate", "mean"),
            std=("estimate", "std"),
            mse=("error2", "mean"),
            mean_se=("se", "mean"),
            coverage=("inside", "mean"),
            converged=("converged", "mean"),
        ).reset_index()
        out.insert(len(keys) + 4, "bias", out["mean"] - out["truth"])
        out.insert(len(keys) + 5, "bias_se", out["std"] / np.sqrt(out["estimated"]))
        out.insert(len(keys) + 7, "rmse", np.sqrt(out.pop("mse")))
        out.insert(out.columns.get_loc("mean_se") + 1, "se_over_std", out["mean_se"] / out["std"])
        return pd.DataFrame(out)

    def covariances(
        self, point: int, estimator: str, converged_only: bool = False
    ) -> dict[str, torch.Tensor | None]:
        """Empirical, mean reported and theoretical covariance of one grid point's estimates.

        Args:
            point: index into :attr:`points`.
            estimator: an estimator's name.
            converged_only: leave out the trials whose fit did not converge.

        Returns:
            A dict with ``"parameters"`` (names), ``"trials"`` (T: the trials whose every
            estimate is usable, see :meth:`summary`), ``"estimates"`` (``(T, p)``),
            ``"empirical"`` (about the sample mean; NaN for T < 2), ``"reported"`` (mean of
            the reported covariances) and ``"theory"`` (None without ``theory``): float64
            tensors ``(p, p)``.
        """
        rows = _at(self._usable(converged_only), self.points[point])
        rows = rows[rows["estimator"] == estimator]
        names = list(dict.fromkeys(rows["parameter"]))
        p = len(names)
        keep = rows["usable"].to_numpy().reshape(-1, p).all(axis=1)
        estimates = torch.tensor(rows["estimate"].to_numpy().reshape(-1, p)[keep])  # a copy
        reported = np.stack(rows["covariance_row"].to_numpy()).reshape(-1, p, p)[keep]
        reported = reported.mean(0) if len(reported) else np.full((p, p), math.nan)
        empirical = torch.full((p, p), math.nan, dtype=torch.float64)
        if estimates.shape[0] >= 2:
            empirical = summarize_estimates(estimates, estimates.mean(0)).covariance
        theory = None if self.theory is None else self.theory(dict(self.points[point]), estimator)
        return {
            "parameters": names,
            "trials": estimates.shape[0],
            "estimates": estimates,
            "empirical": empirical,
            "reported": torch.as_tensor(reported),
            "theory": None if theory is None else torch.as_tensor(theory, dtype=torch.float64),
        }

    def covariance_summary(self, converged_only: bool = False):
        """Empirical vs reported (and theoretical) covariance per grid point x estimator
        (:meth:`covariances`: the trials whose every estimate is usable).

        Columns: the factors, ``estimator``, ``trials``, ``rel_frobenius_reported``
        (``||C_emp - mean C_reported||_F / ||mean C_reported||_F``) and, where ``theory``
        gives a covariance, ``rel_frobenius_theory`` (``||C_emp - C_theory||_F /
        ||C_theory||_F``) and ``rel_frobenius_reported_vs_theory``.
        """
        pd = _pandas()
        rows = []
        for i, point in enumerate(self.points):
            for name in self.estimators:
                c = self.covariances(i, name, converged_only)
                est = c["empirical"]
                row = {**point, "estimator": name, "trials": c["trials"]}
                row["rel_frobenius_reported"] = _relative_frobenius(est, c["reported"])
                theory = c["theory"]
                row["rel_frobenius_theory"] = (
                    math.nan if theory is None else _relative_frobenius(est, theory)
                )
                row["rel_frobenius_reported_vs_theory"] = (
                    math.nan if theory is None else _relative_frobenius(c["reported"], theory)
                )
                rows.append(row)
        return pd.DataFrame(rows)

    def consistency(self, factor: str = "N", converged_only: bool = False):
        """Fitted log-log slopes of ``|bias|`` and ``std`` against ``factor``.

        For a consistent estimator with the usual rate, ``std`` falls like ``N^(-1/2)``
        (slope -1/2) and ``|bias|`` falls at least as fast; a bias that does not shrink
        (slope near 0, with ``|bias|`` well above ``bias_se``) marks an inconsistent one. The
        ``|bias|`` of a consistent estimator is often below its Monte-Carlo error
        ``bias_se``, and its slope then scatters widely; the RMSE, ``sqrt(bias^2 + std^2)``,
        falls like ``N^(-1/2)`` for a consistent estimator and levels off at ``|bias|`` for an
        inconsistent one, with little scatter in either case.

        Returns:
            One row per combination of the other factors x estimator x parameter: those
            columns, ``points`` (values of ``factor`` used), ``bias_slope``, ``std_slope``,
            ``rmse_slope`` (NaN where a value is 0 or NaN, e.g. without truth).

        Raises:
            InputValidationError: ``factor`` is not a numeric grid factor with >= 2 values.
        """
        pd = _pandas()
        values = self.grid.get(factor)
        if values is None or len(set(values)) < 2 or isinstance(values[0], (str, bool)):
            raise InputValidationError(
                f"consistency(factor={factor!r}) needs a numeric grid factor with at least 2 "
                f"values; the grid is {self.grid}."
            )
        summary = self.summary(converged_only=converged_only)
        others = [f for f in self.factors if f != factor]
        rows = []
        for key, group in summary.groupby([*others, "estimator", "parameter"], sort=False):
            x = np.log(group[factor].to_numpy(dtype=float))
            row = dict(zip([*others, "estimator", "parameter"], key, strict=True))
            row["points"] = len(group)
            bias = group["bias"].abs().to_numpy()
            row["bias_slope"] = (
                float(np.polyfit(x, np.log(bias), 1)[0]) if np.all(bias > 0) else math.nan
            )
            row["std_slope"] = float(np.polyfit(x, np.log(group["std"].to_numpy()), 1)[0])
            rmse = group["rmse"].to_numpy()
            row["rmse_slope"] = (
                float(np.polyfit(x, np.log(rmse), 1)[0]) if np.all(rmse > 0) else math.nan
            )
            rows.append(row)
        return pd.DataFrame(rows)

    def normalized_errors(self, converged_only: bool = False):
        """Normalised errors ``z = (estimate - truth) / se`` of every trial.

        For an unbiased estimator whose reported standard errors are right, ``z`` is close to
        N(0, 1) (exactly Student's t with N - p degrees of freedom for least squares with
        Gaussian noise and an estimated noise variance, eq. 4.92-4.93).

        Returns:
            One row per grid point x estimator x parameter x trial with a declared truth, a
            usable estimate (see :meth:`summary`) and a finite positive standard error: the
            factors, ``estimator``, ``parameter``, ``trial``, ``z``.
        """
        keys = [*self.factors, "estimator", "parameter", "trial"]
        frame = self._usable(converged_only)[[*keys, "estimate", "se", "usable"]].merge(
            self._truth_table(), on=[*self.factors, "parameter"], how="inner"
        )
        frame = frame[frame["usable"] & (frame["se"] > 0) & np.isfinite(frame["se"])]
        frame = frame.assign(z=(frame["estimate"] - frame["truth"]) / frame["se"])
        return frame[[*keys, "z"]].reset_index(drop=True)

    def normalized_error_summary(self, converged_only: bool = False):
        """Mean, standard deviation and Kolmogorov-Smirnov distance to N(0, 1) of the
        normalised errors (:meth:`normalized_errors`) per grid point x estimator x parameter.

        Columns: the factors, ``estimator``, ``parameter``, ``trials``, ``mean``, ``std``,
        ``ks_statistic``, ``ks_pvalue`` (:func:`scipy.stats.kstest` against N(0, 1)).
        """
        from scipy.stats import kstest

        pd = _pandas()
        keys = [*self.factors, "estimator", "parameter"]
        rows = []
        for key, group in self.normalized_errors(converged_only).groupby(keys, sort=False):
            z = group["z"].to_numpy()
            test = kstest(z, "norm")
            rows.append(
                {
                    **dict(zip(keys, key, strict=True)),
                    "trials": len(z),
                    "mean": float(z.mean()),
                    "std": float(z.std(ddof=1)),
                    "ks_statistic": float(test.statistic),
                    "ks_pvalue": float(test.pvalue),
                }
            )
        return pd.DataFrame(
            rows, columns=[*keys, "trials", "mean", "std", "ks_statistic", "ks_pvalue"]
        )

    # ------------------------------------------------------------------ report
    def report(
        self,
        out_dir,
        factor: str = "N",
        ellipse: tuple[str, str] | None = None,
        level: float = 0.95,
        converged_only: bool = False,
    ) -> pathlib.Path:
        """Write ``report.md`` with the summary tables (also as CSV) and figures.

        Tables: ``summary``, ``covariance``, ``normalized_errors``
        (:meth:`normalized_error_summary`) and, when ``factor`` is a numeric grid factor with
        >= 2 values, ``consistency``. Figures (PNG, matplotlib's Agg backend):

        * ``bias_std_vs_<factor>.png``: ``|bias|`` and ``std`` against ``factor`` on log-log
          axes with the ``factor^(-1/2)`` reference (numeric ``factor`` only);
        * ``coverage_vs_<factor>.png``: coverage of the ``level`` intervals against
          ``factor``, the nominal level and its binomial band ``level +- z sqrt(level
          (1 - level) / n)`` (``z`` the normal quantile of ``level``, ``n`` the fewest trials
          with usable estimates; numeric ``factor`` only);
        * ``normalized_histograms.png`` and ``normalized_qq.png``: histograms and QQ plots of
          the normalised errors ``(estimate - truth) / se`` against N(0, 1), one panel per
          estimator x parameter, one curve per grid point (needs ``truth``);
        * ``ellipses_<a>_<b>.png``: for the parameters ``ellipse = (a, b)`` (default: the first
          two of the first estimator), one panel per estimator x grid point: the estimates and
          the ``level`` ellipses ``{x: (x - m)' C^-1 (x - m) = chi2_2(level)}`` of the
          empirical, the mean reported and (where ``theory`` gives one) the theoretical
          covariance, all centred on the sample mean ``m``, and the truth;
        * ``se_vs_std.png``: mean reported standard error against the empirical standard
          deviation, with the line of equality.

        Every table and figure takes the usable estimates of :meth:`summary` (with
        ``converged_only``, of the converged fits only).

        Returns:
            The path of ``report.md``.

        Raises:
            InputValidationError: ``ellipse`` names a parameter no estimator has.
        """
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        folder = pathlib.Path(out_dir)
        folder.mkdir(parents=True, exist_ok=True)
        tables = {
            "summary": self.summary(level, converged_only),
            "covariance": self.covariance_summary(converged_only),
            "normalized_errors": self.normalized_error_summary(converged_only),
        }
        values = self.grid.get(factor)
        by_factor = values is not None and len(set(values)) > 1
        by_factor = by_factor and not isinstance(values[0], (str, bool))
        if by_factor:
            tables["consistency"] = self.consistency(factor, converged_only)
        text = [f"# Monte-Carlo study\n\n{self.trials} trials per grid point, seed {self.seed}"]
        text[0] += " (statistics of converged fits only).\n" if converged_only else ".\n"
        for name, table in tables.items():
            table.to_csv(folder / f"{name}.csv", index=False)
            text.append(f"## {name}\n\n{_markdown(table)}")
        figures = []
        if by_factor:
            figures.append(self._plot_bias_std(plt, tables["summary"], factor))
            figures.append(self._plot_coverage(plt, tables["summary"], factor, level))
        if len(tables["normalized_errors"]):
            figures += self._plot_normalized(plt, converged_only)
        figures.append(self._plot_ellipses(plt, ellipse, level, converged_only))
        figures.append(self._plot_se_vs_std(plt, tables["summary"]))
        text.append("## figures\n")
        for fig, name, caption in (f for f in figures if f is not None):
            fig.savefig(folder / name, dpi=150)
            plt.close(fig)
            text.append(f"![{caption}]({name})\n")
        path = folder / "report.md"
        path.write_text("\n".join(text))
        return path

    def _point_label(self, point: dict) -> str:
        return ", ".join(f"{k}={v}" for k, v in point.items()) or "all"

    def _plot_bias_std(self, plt, summary, factor: str):
        others = [f for f in self.factors if f != factor]
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        for key, group in summary.groupby([*others, "estimator", "parameter"], sort=False):
            label = " ".join(str(k) for k in key)
            axes[0].loglog(group[factor], group["bias"].abs(), "o-", label=label)
            axes[1].loglog(group[factor], group["std"], "o-", label=label)
        n = np.array(sorted(set(self.grid[factor])), dtype=float)
        first = summary[summary[factor] == n[0]]["std"].max()
        axes[1].loglog(n, first * np.sqrt(n[0] / n), "k:", label=f"{factor}^(-1/2)")
        axes[0].set_title("|bias|")
        axes[1].set_title("standard deviation")
        axes[0].set_ylabel("|mean estimate - truth|")
        axes[1].set_ylabel("sample standard deviation")
        for ax in axes:
            ax.set_xlabel(factor)
            ax.legend(fontsize=6)
        fig.tight_layout()
        return fig, f"bias_std_vs_{factor}.png", f"bias and std vs {factor}"

    def _plot_coverage(self, plt, summary, factor: str, level: float):
        from scipy.stats import norm

        others = [f for f in self.factors if f != factor]
        fig, ax = plt.subplots(figsize=(6, 4))
        for key, group in summary.groupby([*others, "estimator", "parameter"], sort=False):
            if group["coverage"].notna().any():
                ax.semilogx(group[factor], group["coverage"], "o-", label=" ".join(map(str, key)))
        per_value = summary.groupby(factor)["estimated"].min().clip(lower=1)
        n = per_value.index.to_numpy(dtype=float)
        half = norm.ppf(0.5 + level / 2) * np.sqrt(level * (1 - level) / per_value.to_numpy())
        ax.fill_between(n, level - half, level + half, color="0.85", label="binomial band")
        ax.semilogx(n, np.full_like(n, level), "k:", label=f"nominal {level:g}")
        ax.set_xlabel(factor)
        ax.set_ylabel(f"coverage of {level:g} intervals")
        ax.legend(fontsize=6)
        fig.tight_layout()
        return fig, f"coverage_vs_{factor}.png", f"coverage vs {factor}"

    def _plot_normalized(self, plt, converged_only: bool):
        """Histograms and QQ plots of the normalised errors: rows estimators, columns
        parameters, one curve per grid point (QQ: at most 200 evenly spaced quantiles)."""
        from scipy.stats import norm

        z = self.normalized_errors(converged_only)
        estimators = list(dict.fromkeys(z["estimator"]))
        parameters = {
            e: list(dict.fromkeys(z[z["estimator"] == e]["parameter"])) for e in estimators
        }
        cols = max(len(p) for p in parameters.values())
        size = (3.2 * cols, 2.8 * len(estimators))
        hist, hist_axes = plt.subplots(len(estimators), cols, figsize=size, squeeze=False)
        qq, qq_axes = plt.subplots(len(estimators), cols, figsize=size, squeeze=False)
        edges = np.linspace(-5, 5, 41)
        grid = np.linspace(-5, 5, 201)
        for r, estimator in enumerate(estimators):
            for c in range(cols, len(parameters[estimator]), -1):
                hist_axes[r, c - 1].set_visible(False)
                qq_axes[r, c - 1].set_visible(False)
            for c, parameter in enumerate(parameters[estimator]):
                h, q = hist_axes[r, c], qq_axes[r, c]
                rows = z[(z["estimator"] == estimator) & (z["parameter"] == parameter)]
                for point in self.points:
                    values = _at(rows, point)["z"].to_numpy()
                    if not len(values):
                        continue
                    label = self._point_label(point)
                    h.hist(
                        np.clip(values, -5, 5),
                        bins=edges,
                        density=True,
                        histtype="step",
                        label=label,
                    )
                    probabilities = (np.arange(min(len(values), 200)) + 0.5) / min(len(values), 200)
                    q.plot(
                        norm.ppf(probabilities),
                        np.quantile(values, probabilities),
                        ".",
                        ms=3,
                        label=label,
                    )
                h.plot(grid, norm.pdf(grid), "k:", label="N(0, 1)")
                q.plot([-4, 4], [-4, 4], "k:", label="y = x")
                for ax, ylabel in ((h, "density"), (q, "sample quantile")):
                    ax.set_title(f"{estimator}: {parameter}", fontsize=9)
                    ax.set_ylabel(ylabel)
                    ax.legend(fontsize=6)
                h.set_xlabel("(estimate - truth) / SE")
                q.set_xlabel("N(0, 1) quantile")
        for fig in (hist, qq):
            fig.tight_layout()
        return [
            (hist, "normalized_histograms.png", "histograms of normalised errors"),
            (qq, "normalized_qq.png", "QQ plots of normalised errors against N(0, 1)"),
        ]

    def _plot_ellipses(self, plt, ellipse, level: float, converged_only: bool):
        """The covariance ellipses of two parameters (see :meth:`report`), or None when no
        estimator has two parameters."""
        from scipy.stats import chi2

        names = {
            e: list(dict.fromkeys(g["parameter"]))
            for e, g in self.results.groupby("estimator", sort=False)
        }
        if ellipse is None:
            first = names[next(iter(self.estimators))]
            if len(first) < 2:
                return None
            ellipse = (first[0], first[1])
        a, b = ellipse
        estimators = [e for e in self.estimators if a in names[e] and b in names[e]]
        if not estimators:
            raise InputValidationError(
                f"report(ellipse={ellipse!r}): no estimator has both parameters; their "
                f"parameters are {names}."
            )
        radius = math.sqrt(chi2.ppf(level, 2))
        angle = np.linspace(0, 2 * np.pi, 121)
        circle = np.stack([np.cos(angle), np.sin(angle)])
        rows, cols = len(estimators), len(self.points)
        fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 3.2 * rows), squeeze=False)
        for r, estimator in enumerate(estimators):
            ia, ib = names[estimator].index(a), names[estimator].index(b)
            for i, point in enumerate(self.points):
                ax = axes[r, i]
                c = self.covariances(i, estimator, converged_only)
                est = c["estimates"].numpy()[:, [ia, ib]]
                mean = est.mean(0)
                ax.plot(est[:500, 0], est[:500, 1], ".", ms=2, color="0.6", label="estimates")
                for key, style in (("empirical", "-"), ("reported", "--"), ("theory", ":")):
                    if c[key] is None:
                        continue
                    cov = c[key].numpy()[np.ix_([ia, ib], [ia, ib])]
                    w, v = np.linalg.eigh(cov)
                    xy = mean[:, None] + radius * (v * np.sqrt(np.clip(w, 0, None))) @ circle
                    ax.plot(xy[0], xy[1], style, label=f"{key} {level:g}")
                truth = _at(self._truth_table(), point).set_index("parameter")["truth"]
                if a in truth and b in truth:
                    ax.plot([truth[a]], [truth[b]], "k+", ms=10, label="truth")
                ax.set_title(f"{estimator}, {self._point_label(point)}", fontsize=9)
                ax.set_xlabel(a)
                ax.set_ylabel(b)
                ax.legend(fontsize=6)
        fig.tight_layout()
        return fig, f"ellipses_{a}_{b}.png", f"covariance ellipses of {a} and {b}"

    def _plot_se_vs_std(self, plt, summary):
        fig, ax = plt.subplots(figsize=(5, 4))
        for name, group in summary.groupby("estimator", sort=False):
            ax.loglog(group["std"], group["mean_se"], "o", label=name)
        ends = [summary[["std", "mean_se"]].min().min(), summary[["std", "mean_se"]].max().max()]
        ax.loglog(ends, ends, "k:", label="equality")
        ax.set_xlabel("empirical standard deviation")
        ax.set_ylabel("mean reported standard error")
        ax.legend(fontsize=7)
        fig.tight_layout()
        return fig, "se_vs_std.png", "reported SE vs empirical std"


class _NamesUnknown(Exception):
    """An estimator failed for every trial of a chunk computed before any chunk told its
    parameter names (``args[0]``: the error); the chunk is computed again at the end of
    :meth:`Study.run`."""


def _parameter_names(done: dict) -> dict:
    """Estimator -> its parameter names, from the finished chunks' rows ``done``."""
    names = {}
    for frame in done.values():
        for estimator, rows in frame.groupby("estimator", sort=False):
            if estimator not in names:
                names[estimator] = list(dict.fromkeys(rows["parameter"]))
    return names


def _fit_or_split(estimator, data: IOData, lo: int, hi: int) -> list[tuple]:
    """``estimator`` on the data sets ``lo:hi`` of ``data``: ``[(lo, hi, result, None)]``, or,
    where it raises a project error, the parts of its two halves, down to single data sets
    ``(i, i + 1, None, error)``."""
    try:
        part = data if (lo, hi) == (0, data.batch_shape[0]) else data[lo:hi]
        return [(lo, hi, estimator(part), None)]
    except StudyDeclarationError:
        raise
    except RKIdentError as error:
        if hi - lo == 1:
            return [(lo, hi, None, error)]
        mid = (lo + hi) // 2
        return _fit_or_split(estimator, data, lo, mid) + _fit_or_split(estimator, data, mid, hi)


def _check_result(name: str, result) -> None:
    """Raise unless ``result`` has what a results row needs (a :class:`FitResult` does)."""
    needed = ("theta", "standard_errors", "covariance", "converged", "loss_history")
    missing = [a for a in (*needed, "parameter_names") if not hasattr(result, a)]
    if missing:
        raise InputValidationError(
            f"estimator {name!r} returned a {type(result).__name__} without {missing}; it must "
            "return a FitResult (anything sysid.fit returns)."
        )


def _rows(name: str, names: list[str], trials: np.ndarray, result, error, seconds: float):
    """The results rows of one estimator's ``result`` for ``trials``, or of the ``error`` it
    raised for them (NaN, not converged); ``seconds`` per trial."""
    pd = _pandas()
    n, p = len(trials), len(names)
    if error is not None:
        nan = np.full((n, p), math.nan)
        theta, se, cov = nan, nan, np.full((n, p, p), math.nan)
        converged, loss = np.zeros(n, dtype=bool), np.full(n, math.nan)
        message = f"{type(error).__name__}: {error}"
    else:
        theta = result.theta.detach()
        if tuple(theta.shape) != (n, p) or list(result.parameter_names) != names:
            raise InputValidationError(
                f"estimator {name!r} returned theta of shape {tuple(theta.shape)} with the "
                f"parameters {list(result.parameter_names)} for a chunk of {n} data sets; "
                f"expected ({n}, {p}) with {names}."
            )
        theta = theta.double().cpu().numpy()
        se = result.standard_errors.detach().double().cpu().numpy().reshape(n, p)
        cov = result.covariance.detach().double().cpu().numpy().reshape(n, p, p)
        converged = result.converged.detach().cpu().numpy().reshape(n).astype(bool)
        loss = result.loss_history.detach()[-1].double().cpu().numpy().reshape(n)
        message = ""
    return pd.DataFrame(
        {
            "estimator": name,
            "trial": np.repeat(trials, p),
            "parameter": np.tile(names, n),
            "estimate": theta.reshape(-1),
            "se": se.reshape(-1),
            "converged": np.repeat(converged, p),
            "loss": np.repeat(loss, p),
            "time": seconds,
            "covariance_row": list(cov.reshape(n * p, p)),
            "error": message,
        }
    )


def _at(frame, point: dict):
    """The rows of ``frame`` at grid point ``point`` (factor -> value)."""
    mask = np.ones(len(frame), dtype=bool)
    for factor, value in point.items():
        mask &= (frame[factor] == value).to_numpy()
    return frame[mask]


def _relative_frobenius(a: torch.Tensor, b: torch.Tensor) -> float:
    """``||a - b||_F / ||b||_F``."""
    return float(torch.linalg.matrix_norm(a - b) / torch.linalg.matrix_norm(b))
