"""Input/output data sets for discrete-time system identification.

:class:`IOData` holds sampled input ``u`` and output ``y`` of one experiment, of several
experiments of different lengths (kept apart: each keeps its own initial conditions), or a
batch of equally long data sets (leading batch dimensions, e.g. 2000 Monte-Carlo noise
realisations in one object).

Shapes (sequences are ``(*batch, time, channels)``, DESIGN.md):

- ``u``: ``(N,)`` (one input), ``(N, nu)``, or ``(*batch, N, nu)``;
- ``y``: ``(N,)`` (one output), ``(N, ny)``, or ``(*batch, N, ny)``.

The batch shapes of ``u`` and ``y`` are broadcast against each other (a shared input with a
batch of noisy outputs is stored as an expanded view, not copied). Integer and boolean
arrays become float64; float32 and float64 are kept (mixed: promoted to float64); anything
else (complex, float16) is rejected. Non-finite values raise :class:`InputValidationError`
naming the signal, experiment, batch index, sample and channel.

Several experiments: ``IOData.experiments([d1, d2, ...])`` returns one object whose
``.experiment_list`` holds the parts; ``.u``/``.y`` of such an object are the parts
concatenated along time for convenience (fit measures, plots) and must NOT be filtered as one
signal: models and regressors work experiment by experiment and stack the results.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from integrators._options import check_positive
from integrators.errors import InputValidationError

__all__ = ["INTERSAMPLE", "IOData", "as_signal"]

#: How the input behaves between samples (MATLAB's ``InterSample`` names): ``"zoh"`` held
#: constant, ``"foh"`` linear between samples, ``"cubic"`` a cubic spline through the samples,
#: ``"bl"`` band-limited (the trigonometric interpolant of the periodic record).
INTERSAMPLE = ("zoh", "foh", "cubic", "bl")


def as_signal(x, name: str, dtype: torch.dtype | None = None, device=None) -> torch.Tensor:
    """Convert ``x`` to a float tensor of shape ``(*batch, N, channels)``.

    ``(N,)`` becomes ``(N, 1)``; ``(N, c)`` stays; more dimensions are ``(*batch, N, c)``.
    Integer/bool data become float64 (or ``dtype``); float16/complex are rejected.
    """
    if isinstance(x, torch.Tensor):
        t = x
    else:
        try:
            arr = np.asarray(x)
        except ValueError as exc:  # sequences of different lengths
            raise InputValidationError(
                f"{name} could not be converted to a numeric array ({exc}); data sets of "
                "different lengths are separate experiments: IOData.experiments([...])."
            ) from exc
        if arr.dtype == object:
            raise InputValidationError(f"{name} could not be converted to a numeric array.")
        t = torch.as_tensor(arr)
    if t.is_complex():
        raise InputValidationError(f"{name} is complex; only real float32/float64 data are used.")
    if not t.is_floating_point():
        t = t.to(torch.float64)
    elif t.dtype not in (torch.float32, torch.float64):
        raise InputValidationError(
            f"{name} has dtype {t.dtype}; use float32 or float64 (e.g. x.double())."
        )
    if dtype is not None or device is not None:
        t = t.to(device=device, dtype=dtype)
    if t.ndim == 0:
        raise InputValidationError(f"{name} is a scalar; expected a sequence of shape (N,).")
    if t.ndim == 1:
        t = t.unsqueeze(-1)
    return t


def _check_finite(x: torch.Tensor, name: str, experiment: int | None) -> None:
    if bool(torch.isfinite(x.sum())):  # one cheap reduction; locate only on failure
        return
    bad = ~torch.isfinite(x)
    if bool(bad.any()):
        idx = torch.nonzero(bad)[0].tolist()
        *batch, k, c = idx
        where = f"sample {k}, channel {c}"
        if batch:
            where += f", batch index {tuple(batch)}"
        if experiment is not None:
            where += f", experiment {experiment}"
        value = x[tuple(idx)].item()
        raise InputValidationError(
            f"{name} is not finite ({value}) at {where}; {int(bad.sum())} non-finite value(s) "
            "in all. Remove, interpolate or split the record there (IOData.experiments)."
        )


def _indexed_dims(index) -> int:
    """How many dimensions one entry of an index consumes (a boolean mask: its own)."""
    if index is None or index is Ellipsis:
        return 0
    if isinstance(index, (torch.Tensor, np.ndarray)) and index.dtype in (torch.bool, np.bool_):
        return index.ndim
    return 1


class IOData:
    """Sampled input/output data: one experiment, several experiments, or a batch.

    Args:
        u: input, ``(N,)``, ``(N, nu)`` or ``(*batch, N, nu)``.
        y: output, ``(N,)``, ``(N, ny)`` or ``(*batch, N, ny)``; same ``N`` as ``u``.
        Ts: sample time in seconds (> 0).
        intersample: how the input behaves between samples, one of :data:`INTERSAMPLE`
            (default ``"zoh"``). Discrete-time models ignore it; every simulation of a
            continuous-time model (:mod:`sysid.continuous`) reconstructs the input with it.

    Attributes:
        u, y: ``(*batch, N, nu)`` and ``(*batch, N, ny)`` tensors (for several experiments:
            the parts concatenated along time, see the module docstring).
        Ts: sample time.
        intersample: the intersample behaviour of the input.
        experiment_list: tuple of single-experiment :class:`IOData` (``(self,)`` for one).
    """

    def __init__(
        self,
        u,
        y,
        Ts: float = 1.0,
        *,
        intersample: str = "zoh",
        _experiment: int | None = None,
    ):
        where = "" if _experiment is None else f" of experiment {_experiment}"
        if intersample not in INTERSAMPLE:
            raise InputValidationError(
                f"intersample must be one of {INTERSAMPLE}, got {intersample!r}: 'zoh' for an "
                "input held between samples (a digital controller's output), 'foh' for a "
                "piecewise-linear one, 'cubic' for a smooth one, 'bl' for a band-limited "
                "(e.g. multisine) excitation sampled without aliasing."
            )
        u = as_signal(u, "u" + where)
        y = as_signal(y, "y" + where)
        dtype = torch.promote_types(u.dtype, y.dtype)
        if u.device != y.device:
            raise InputValidationError(f"u is on {u.device} but y is on {y.device}.")
        u, y = u.to(dtype), y.to(dtype)
        if u.shape[-2] != y.shape[-2]:
            raise InputValidationError(
                f"u has {u.shape[-2]} samples but y has {y.shape[-2]}{where}; u and y must have "
                "the same length N along the time axis (dimension -2 of (*batch, N, channels))."
            )
        if u.shape[-2] < 1:
            raise InputValidationError(f"the data set{where} is empty (N = 0 samples).")
        try:
            batch = torch.broadcast_shapes(u.shape[:-2], y.shape[:-2])
        except RuntimeError as err:
            raise InputValidationError(
                f"batch shapes of u {tuple(u.shape[:-2])} and y {tuple(y.shape[:-2])} do not "
                "broadcast."
            ) from err
        Ts = check_positive(Ts, "sample time Ts", " (seconds)")
        _check_finite(u, "u", _experiment)
        _check_finite(y, "y", _experiment)
        self.u = u.expand(*batch, *u.shape[-2:])
        self.y = y.expand(*batch, *y.shape[-2:])
        self.Ts = Ts
        self.intersample = intersample
        self.experiment_list: tuple[IOData, ...] = (self,)

    # ------------------------------------------------------------------ construction
    @classmethod
    def experiments(cls, parts: Sequence[IOData]) -> IOData:
        """Combine several experiments (different lengths allowed) without concatenating them.

        Args:
            parts: :class:`IOData` objects or ``(u, y)`` / ``(u, y, Ts)`` tuples (validated
                here, with the experiment index in error messages). All parts must share
                ``Ts``, ``nu``, ``ny``, batch shape, dtype and device.
        """
        parts = list(parts)
        if not parts:
            raise InputValidationError("IOData.experiments needs at least one experiment.")
        flat: list[IOData] = []
        for i, p in enumerate(parts):
            if isinstance(p, (tuple, list)):
                p = IOData(*p, _experiment=i)
            if not isinstance(p, IOData):
                raise InputValidationError(f"experiment {i} is {type(p).__name__}, not IOData.")
            flat.extend(p.experiment_list)
        ref = flat[0]
        for i, p in enumerate(flat[1:], start=1):
            for attr in ("Ts", "intersample", "nu", "ny", "batch_shape", "dtype", "device"):
                if getattr(p, attr) != getattr(ref, attr):
                    raise InputValidationError(
                        f"experiment {i} has {attr} = {getattr(p, attr)} but experiment 0 has "
                        f"{getattr(ref, attr)}; all experiments must agree."
                    )
        if len(flat) == 1:
            return flat[0]
        out = cls.__new__(cls)
        out.u = torch.cat([p.u for p in flat], dim=-2)
        out.y = torch.cat([p.y for p in flat], dim=-2)
        out.Ts = ref.Ts
        out.intersample = ref.intersample
        out.experiment_list = tuple(flat)
        return out

    @classmethod
    def cat(cls, parts: Sequence[IOData]) -> IOData:
        """Join data sets along the first batch dimension (e.g. blocks of Monte-Carlo trials),
        experiment by experiment, keeping ``Ts`` and ``intersample``.

        Raises:
            InputValidationError: a part that is not an IOData with a batch dimension, or
                parts that differ in ``Ts``, ``intersample``, experiment lengths, channels,
                dtype, device or later batch dimensions.
        """
        parts = list(parts)
        if not parts:
            raise InputValidationError("IOData.cat needs at least one data set.")
        ref = parts[0]
        for i, p in enumerate(parts):
            if not isinstance(p, IOData) or len(p.batch_shape) == 0:
                raise InputValidationError(
                    f"IOData.cat joins along the first batch dimension: part {i} is "
                    f"{p!r}, not an IOData with a batch dimension."
                )
            for attr in ("Ts", "intersample", "lengths", "nu", "ny", "dtype", "device"):
                if getattr(p, attr) != getattr(ref, attr):
                    raise InputValidationError(
                        f"part {i} has {attr} = {getattr(p, attr)} but part 0 has "
                        f"{getattr(ref, attr)}; the parts must agree."
                    )
            if p.batch_shape[1:] != ref.batch_shape[1:]:
                raise InputValidationError(
                    f"part {i} has batch shape {tuple(p.batch_shape)} but part 0 has "
                    f"{tuple(ref.batch_shape)}; only the first batch dimension may differ."
                )
        experiments = [
            cls._trusted(
                torch.cat([p.experiment_list[e].u for p in parts]),
                torch.cat([p.experiment_list[e].y for p in parts]),
                ref.Ts,
                ref.intersample,
            )
            for e in range(ref.n_experiments)
        ]
        return experiments[0] if len(experiments) == 1 else cls.experiments(experiments)

    @classmethod
    def _trusted(
        cls, u: torch.Tensor, y: torch.Tensor, Ts: float, intersample: str = "zoh"
    ) -> IOData:
        out = cls.__new__(cls)
        out.u, out.y, out.Ts, out.intersample = u, y, Ts, intersample
        out.experiment_list = (out,)
        return out

    def _map(self, fn) -> IOData:
        """Apply ``fn(u, y) -> (u, y)`` to every experiment and recombine."""
        parts = [IOData._trusted(*fn(p.u, p.y), p.Ts, p.intersample) for p in self.experiment_list]
        return parts[0] if len(parts) == 1 else IOData.experiments(parts)

    # ------------------------------------------------------------------ properties
    @property
    def N(self) -> int:
        """Number of samples (all experiments together)."""
        return self.u.shape[-2]

    @property
    def nu(self) -> int:
        return self.u.shape[-1]

    @property
    def ny(self) -> int:
        return self.y.shape[-1]

    @property
    def batch_shape(self) -> torch.Size:
        return self.u.shape[:-2]

    @property
    def n_experiments(self) -> int:
        return len(self.experiment_list)

    @property
    def lengths(self) -> list[int]:
        """Number of samples of each experiment."""
        return [p.N for p in self.experiment_list]

    def samples_after(self, skip: int) -> torch.Tensor:
        """Indices (along the sample axis of ``u`` and ``y``) of the samples that remain when
        the first ``skip`` samples of every experiment are left out (``int64``).

        Raises:
            InputValidationError: ``skip`` is not an integer in ``[0, N_e - 2]`` for every
                experiment (at least two samples of each must remain).
        """
        shortest = min(self.lengths)
        integral = isinstance(skip, (int, float, np.integer, np.floating)) and float(skip) % 1 == 0
        if isinstance(skip, bool) or not integral or not 0 <= skip <= shortest - 2:
            raise InputValidationError(
                f"skip must be an integer with 0 <= skip <= {shortest - 2} (at least 2 samples "
                f"of the shortest experiment, N = {shortest}, remain), got {skip!r}."
            )
        ends = np.cumsum(self.lengths)
        starts = ends - np.asarray(self.lengths)
        keep = [torch.arange(int(a) + int(skip), int(b)) for a, b in zip(starts, ends, strict=True)]
        return torch.cat(keep).to(self.device)

    @property
    def dtype(self) -> torch.dtype:
        return self.u.dtype

    @property
    def device(self) -> torch.device:
        return self.u.device

    @property
    def t(self) -> torch.Tensor:
        """Sample times ``k * Ts`` of a single experiment, shape ``(N,)``.

        Raises:
            InputValidationError: the data hold several experiments (each starts at 0: use
                ``data.experiment_list[e].t``).
        """
        if self.n_experiments > 1:
            raise InputValidationError(
                f"IOData.t is the time grid of one experiment; these data hold "
                f"{self.n_experiments} (each starts at t = 0): use data.experiment_list[e].t."
            )
        return torch.arange(self.N, dtype=self.dtype, device=self.device) * self.Ts

    def __repr__(self) -> str:
        return (
            f"IOData(N={self.lengths if self.n_experiments > 1 else self.N}, nu={self.nu}, "
            f"ny={self.ny}, batch_shape={tuple(self.batch_shape)}, Ts={self.Ts}, "
            f"intersample={self.intersample!r}, "
            f"dtype={self.dtype})"
        )

    # ------------------------------------------------------------------ operations
    def to(self, device=None, dtype: torch.dtype | None = None) -> IOData:
        """Copy to another device and/or float dtype."""
        if dtype is not None and dtype not in (torch.float32, torch.float64):
            raise InputValidationError(f"dtype must be float32 or float64, got {dtype}.")
        return self._map(lambda u, y: (u.to(device, dtype), y.to(device, dtype)))

    def __getitem__(self, index) -> IOData:
        """Select data sets from the batch dimensions, e.g. ``data[3]`` or ``data[:10]``."""
        if len(self.batch_shape) == 0:
            raise InputValidationError("this IOData has no batch dimension to index.")
        if not isinstance(index, tuple):
            index = (index,)
        consumed = sum(_indexed_dims(i) for i in index)
        if consumed > len(self.batch_shape):
            raise InputValidationError(
                f"IOData[{index!r}] indexes {consumed} dimensions, but the data have "
                f"{len(self.batch_shape)} batch dimension(s) {tuple(self.batch_shape)}; samples "
                "and channels are not indexed this way (use split() for a part of the record)."
            )
        # the samples and channels stay whole, also behind an Ellipsis
        full = (*index, slice(None), slice(None))
        if not any(i is Ellipsis for i in index):
            full = (*index, Ellipsis, slice(None), slice(None))
        try:
            return self._map(lambda u, y: (u[full], y[full]))
        except (IndexError, ValueError, RuntimeError) as exc:
            raise InputValidationError(f"IOData[{index!r}]: {exc}") from exc

    def detrend(self, kind: str = "mean") -> IOData:
        """Remove the mean (``"mean"``) or a least-squares straight line (``"linear"``).

        Applied per experiment, batch member and channel, to ``u`` and ``y`` alike.
        """
        if kind not in ("mean", "linear", "constant"):
            raise InputValidationError(f"detrend kind must be 'mean' or 'linear', got {kind!r}.")

        def remove(x: torch.Tensor) -> torch.Tensor:
            x = x - x.mean(dim=-2, keepdim=True)
            if kind == "linear" and x.shape[-2] > 1:
                k = torch.arange(x.shape[-2], dtype=x.dtype, device=x.device)
                k = (k - k.mean()).unsqueeze(-1)
                slope = (k * x).sum(-2, keepdim=True) / (k * k).sum()
                x = x - slope * k
            return x

        return self._map(lambda u, y: (remove(u), remove(y)))

    def split(self, at: float | int) -> tuple[IOData, IOData]:
        """Split into (estimation, validation) parts.

        Args:
            at: a fraction in (0, 1) (each experiment is split at ``round(at * N_e)``) or an
                integer sample index ``0 < at < N`` (single-experiment data only).
        """
        if isinstance(at, bool) or not isinstance(at, (int, float, np.integer, np.floating)):
            raise InputValidationError(f"split point must be a fraction or an index, got {at!r}.")
        if isinstance(at, (int, np.integer)):
            if self.n_experiments > 1:
                raise InputValidationError(
                    "an integer split index is ambiguous for several experiments; give a "
                    "fraction, or split the parts in .experiment_list yourself."
                )
            cuts = [int(at)]
        else:
            if not 0.0 < at < 1.0:
                raise InputValidationError(f"split fraction must be in (0, 1), got {at}.")
            cuts = [int(round(at * n)) for n in self.lengths]
        heads, tails = [], []
        for i, (p, k) in enumerate(zip(self.experiment_list, cuts, strict=True)):
            if not 0 < k < p.N:
                raise InputValidationError(
                    f"split point {k} leaves an empty part of experiment {i} (N = {p.N}); "
                    "choose 0 < index < N."
                )
            heads.append(IOData._trusted(p.u[..., :k, :], p.y[..., :k, :], p.Ts, p.intersample))
            tails.append(IOData._trusted(p.u[..., k:, :], p.y[..., k:, :], p.Ts, p.intersample))
        return IOData.experiments(heads), IOData.experiments(tails)
