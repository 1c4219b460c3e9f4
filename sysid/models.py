"""Discrete-time polynomial model structures: FIR, ARX, OE, ARMAX, Box-Jenkins (notes §4.6).

The general model (MATLAB's ``idpoly``), for inputs ``u_1 .. u_nu`` and white noise ``e``::

    A(q) y_t = sum_i  B_i(q) / F_i(q)  u_i(t - nk_i)  +  C(q) / D(q)  e_t

so ``G_i = q^-nk_i B_i / (A F_i)`` and ``H = C / (A D)``, with the polynomials in the backward
shift ``q^-1`` (MATLAB's sign and index conventions)::

    A = 1 + a1 q^-1 + ... + a_na q^-na           C = 1 + c1 q^-1 + ... + c_nc q^-nc
    B_i = b1 + b2 q^-1 + ... + b_nb q^-(nb-1)    D = 1 + d1 q^-1 + ... + d_nd q^-nd
    F_i = 1 + f1 q^-1 + ... + f_nf q^-nf

Orders count coefficients as in MATLAB: ``na`` is the number of a-coefficients ``a1..a_na``,
``nb`` the number of b-coefficients, ``nc, nd, nf`` likewise, and ``nk`` the input delay in
samples (``nk = 0``: ``b1`` multiplies ``u_t``). ``nb, nf, nk`` may be per-input lists.
NOTE the notes' sign convention differs: their (4.94)/(4.117) ``y_k = sum b_i u_{k-i} +
sum a_i y_{k-i}`` has ``A = 1 - sum a_i z^-i`` (4.119), i.e. notes' ``a_i`` = ``-a_i`` here, and
their ``b_0`` (no delay) is ``b1`` with ``nk = 0``.

Structures: ``FIR`` (B), ``ARX`` (A, B), ``OE`` (B, F), ``ARMAX`` (A, B, C), ``BJ`` (B, C, D, F),
and the general :class:`PolynomialModel`.

API used by the estimators (``sysid.fit`` and friends):

- ``predict(data, horizon=1, theta=None) -> (*batch, N, 1)``: the k-step-ahead predictor
  ``yhat = W_k G u + (1 - W_k) y``, ``W_k = Hbar_k H^-1`` where ``Hbar_k`` is the first
  ``k`` impulse-response terms of ``H``; for ``k = 1`` this is eq. (4.130)
  ``yhat = H^-1 G u + (1 - H^-1) y``; ``horizon=math.inf`` (or ``None``) is ``simulate``.
  Initial conditions: zero (all signals at rest before sample 0), per experiment.
- ``simulate(u, zi=None, theta=None) -> (*batch, N, 1)``: the noise-free free run ``G u``.
- ``prediction_errors(data)`` = ``y - predict(data)``; ``simulation_errors(data)`` =
  ``y - simulate(data)`` (both ``(*batch, N, 1)``).
- ``parameter_vector() -> (*batch, p)`` ordered a, b (input 1, 2, ..), c, d, f (input 1, ..);
  ``set_parameter_vector(theta)``; ``parameter_names()`` ("a1", "b1", "c1", "d1", "f1"; with
  several inputs "b1_u1", "f2_u2", ...); ``n_params``. Passing ``theta=`` to the evaluation
  methods uses that vector instead of the module's parameters (differentiable in ``theta``,
  e.g. for ``torch.func.jacfwd``).
- FIR and ARX (``is_linear_in_parameters = True``): ``regression(data) -> (Phi, target)``
  with ``Phi (*batch, M, p)`` and ``target (*batch, M)``: one row per sample where every lag is
  inside the experiment (eq. 4.111 with MATLAB signs: row ``[-y_{t-1}.. -y_{t-na},
  u_{t-nk}.. u_{t-nk-nb+1}]``), experiments stacked.
- ``to_control(noise=False)`` (python-control ``TransferFunction`` with ``dt = Ts``; a list
  for a batched model; ``model[i]`` is the unbatched model ``i``), ``poles()``, ``zeros()``,
  ``is_stable()``, ``frequency_response(omega)``, ``stabilize()``.

Every B/F, C/D filtering uses :func:`sysid.filters.iir_filter` (no Python loop over samples,
inputs or batch members).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from integrators._options import check_positive
from integrators.errors import InputValidationError

from .data import IOData, as_signal
from .filters import iir_filter, poly_mul

__all__ = ["ARMAX", "ARX", "BJ", "FIR", "OE", "PolynomialModel"]


def _is_integer(value) -> bool:
    """True for a Python or numpy integer, False for a bool and everything else."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _integer_list(value, repeat: int, message: str) -> list[int]:
    """``value`` (an integer, taken ``repeat`` times, or a sequence of integers) as a list of
    integers >= 0; raises InputValidationError with ``message`` otherwise (a bool, a float such
    as 2.0, a string)."""
    try:
        values = [value] * repeat if _is_integer(value) else list(value)
    except TypeError:  # not iterable
        values = [value]
    if isinstance(value, str) or not all(_is_integer(v) and v >= 0 for v in values):
        raise InputValidationError(message)
    return [int(v) for v in values]


def _per_input(value, n_inputs: int, name: str) -> list[int]:
    """``value`` (an integer or one per input) as a list of ``n_inputs`` integers >= 0."""
    values = _integer_list(
        value,
        n_inputs,
        f"{name} must be an integer >= 0 or a list of them (one per input), got {value!r}: "
        "orders count coefficients and nk counts samples, so they are whole numbers (a bool or "
        "a float such as 2.0 is refused, not rounded).",
    )
    if len(values) != n_inputs:
        raise InputValidationError(
            f"{name} has {len(values)} entries but the model has {n_inputs} inputs."
        )
    return values


def _order(value, name: str) -> int:
    if not _is_integer(value) or value < 0:
        raise InputValidationError(
            f"{name} must be an integer >= 0, got {value!r}: orders count coefficients, so "
            "they are whole numbers (a bool or a float such as 2.0 is refused, not rounded)."
        )
    return int(value)


def _batch_shape(batch_shape, what: str = "models") -> torch.Size:
    """``batch_shape`` (an integer or a sequence of integers, each >= 0) as a ``torch.Size``;
    ``what`` the batch holds, for the message."""
    return torch.Size(
        _integer_list(
            batch_shape,
            1,
            f"batch_shape must be an integer >= 0 or a sequence of them (the number of {what} "
            f"along each batch dimension), got {batch_shape!r}.",
        )
    )


def _monic(tail: torch.Tensor) -> torch.Tensor:
    """``[1, tail...]`` along the last dim."""
    return F.pad(tail, (1, 0), value=1.0)


def _sum_inputs(y: torch.Tensor) -> torch.Tensor:
    """Sum the per-input responses ``(*batch, nu, N) -> (*batch, N)`` (a view when nu = 1,
    taken by ``squeeze``, whose backward is a view too: no zero-filled gradient buffer)."""
    return y.squeeze(-2) if y.shape[-2] == 1 else y.sum(-2)


#: Sample time of a model built without one (seconds); :func:`sysid.fit` gives the fitted
#: model its data's.
DEFAULT_TS = 1.0


def _roots(tail: torch.Tensor) -> torch.Tensor:
    """Roots in z of ``z^n + t_1 z^(n-1) + ... + t_n`` (batched, via companion eigenvalues);
    NaN for a polynomial with a non-finite coefficient (e.g. a failed estimate)."""
    n = tail.shape[-1]
    if n == 0:
        return torch.zeros(*tail.shape[:-1], 0, dtype=torch.complex128, device=tail.device)
    finite = torch.isfinite(tail).all(dim=-1, keepdim=True)
    comp = torch.zeros(*tail.shape[:-1], n, n, dtype=tail.dtype, device=tail.device)
    comp[..., 0, :] = -torch.where(finite, tail, 0.0)  # LAPACK refuses non-finite entries
    if n > 1:
        idx = torch.arange(n - 1, device=tail.device)
        comp[..., idx + 1, idx] = 1.0
    roots = torch.linalg.eigvals(comp)
    return torch.where(finite, roots, torch.full_like(roots, math.nan))


def _monic_from_roots(roots: torch.Tensor) -> torch.Tensor:
    """Real tail ``t_1..t_n`` of ``prod (z - r)`` for conjugate-closed roots (batched)."""
    c = torch.ones(*roots.shape[:-1], 1, dtype=roots.dtype, device=roots.device)
    for j in range(roots.shape[-1]):  # loop over the polynomial order
        c = F.pad(c, (0, 1)) - roots[..., j : j + 1] * F.pad(c, (1, 0))
    return c[..., 1:].real


class PolynomialModel(nn.Module):
    """General SISO/MISO polynomial model ``A y = sum B_i/F_i u_i(t-nk_i) + C/D e``.

    Args:
        na, nc, nd: numbers of coefficients of A, C, D.
        nb, nf, nk: numbers of coefficients of each B_i, F_i and the input delays (int or a
            list with one entry per input).
        n_inputs: number of inputs ``nu``.
        batch_shape: leading batch shape of every parameter (one model per data set).
        dtype: float64 (default) or float32.
        Ts: sample time in seconds (finite, > 0) used by :meth:`to_control` and
            :meth:`frequency_response`; a fitted model takes its data's (:func:`sysid.fit`
            refuses a model whose ``Ts`` is set to another value than the default and the
            data's).

    Parameters start at zero (``G = 0`` when nb > 0 means B = 0; A = C = D = F = 1).
    """

    is_linear_in_parameters = False

    def __init__(
        self,
        na: int = 0,
        nb: int | Sequence[int] = 0,
        nc: int = 0,
        nd: int = 0,
        nf: int | Sequence[int] = 0,
        nk: int | Sequence[int] = 1,
        *,
        n_inputs: int = 1,
        batch_shape: int | Sequence[int] = (),
        dtype: torch.dtype = torch.float64,
        device=None,
        Ts: float = DEFAULT_TS,
    ):
        super().__init__()
        if not _is_integer(n_inputs) or n_inputs < 1:
            raise InputValidationError(f"n_inputs must be an integer >= 1, got {n_inputs!r}.")
        if dtype not in (torch.float32, torch.float64):
            raise InputValidationError(f"dtype must be float32 or float64, got {dtype}.")
        self.n_inputs = int(n_inputs)
        self.na, self.nc, self.nd = _order(na, "na"), _order(nc, "nc"), _order(nd, "nd")
        self.nb = _per_input(nb, self.n_inputs, "nb")
        self.nf = _per_input(nf, self.n_inputs, "nf")
        self.nk = _per_input(nk, self.n_inputs, "nk")
        self.batch_shape = _batch_shape(batch_shape)
        self.Ts = Ts

        def param(n: int) -> nn.Parameter:
            return nn.Parameter(torch.zeros(*self.batch_shape, n, dtype=dtype, device=device))

        self.a, self.c, self.d = param(self.na), param(self.nc), param(self.nd)
        self.b = nn.ParameterList([param(n) for n in self.nb])
        self.f = nn.ParameterList([param(n) for n in self.nf])
        # (letter, size) of each block of theta, fixed by the orders (see _blocks)
        self._layout = [("a", self.na), *(("b", n) for n in self.nb), ("c", self.nc)]
        self._layout += [("d", self.nd), *(("f", n) for n in self.nf)]

    @property
    def Ts(self) -> float:
        """Sample time in seconds (finite, > 0), checked when set."""
        return self._Ts

    @Ts.setter
    def Ts(self, value) -> None:
        self._Ts = check_positive(
            value,
            "sample time Ts",
            f" (seconds); leave it out for the default {DEFAULT_TS} s (sysid.fit gives the "
            "fitted model its data's)",
        )

    # ------------------------------------------------------------------ parameters
    def _blocks(self) -> list[tuple[str, int, nn.Parameter]]:
        """(letter, input index or -1, parameter) in parameter-vector order."""
        out = [("a", -1, self.a)]
        out += [("b", i, p) for i, p in enumerate(self.b)]
        out += [("c", -1, self.c), ("d", -1, self.d)]
        out += [("f", i, p) for i, p in enumerate(self.f)]
        return out

    @property
    def n_params(self) -> int:
        return self.na + sum(self.nb) + self.nc + self.nd + sum(self.nf)

    def parameter_names(self) -> list[str]:
        names = []
        for letter, i, p in self._blocks():
            suffix = f"_u{i + 1}" if i >= 0 and self.n_inputs > 1 else ""
            names += [f"{letter}{j + 1}{suffix}" for j in range(p.shape[-1])]
        return names

    def parameter_vector(self) -> torch.Tensor:
        """``(*batch, p)`` concatenation a, b_1.., c, d, f_1.. (see :meth:`parameter_names`)."""
        return torch.cat([p for _, _, p in self._blocks()], dim=-1)

    def _split(self, theta: torch.Tensor) -> dict[str, list[torch.Tensor]]:
        if theta.shape[-1] != self.n_params:
            raise InputValidationError(
                f"theta has {theta.shape[-1]} entries; this model has {self.n_params} "
                f"parameters {self.parameter_names()}."
            )
        parts = torch.split(theta, [size for _, size in self._layout], dim=-1)
        out: dict[str, list[torch.Tensor]] = {k: [] for k in "abcdf"}
        for (letter, _), part in zip(self._layout, parts, strict=True):
            out[letter].append(part)
        return out

    def _coefficients(self, theta: torch.Tensor | None) -> dict[str, list[torch.Tensor]]:
        if theta is None:
            return {
                "a": [self.a],
                "b": list(self.b),
                "c": [self.c],
                "d": [self.d],
                "f": list(self.f),
            }
        return self._split(theta)

    @torch.no_grad()
    def set_parameter_vector(self, theta: torch.Tensor) -> None:
        """Copy ``theta`` (``(*batch, p)``, broadcast to the model's batch) into the parameters."""
        theta = torch.as_tensor(theta, dtype=self.a.dtype, device=self.a.device)
        parts = self._split(theta)
        batch = theta.shape[:-1]
        try:
            fits = torch.broadcast_shapes(batch, self.batch_shape) == self.batch_shape
        except RuntimeError:  # the shapes do not broadcast
            fits = False
        if not fits:
            raise InputValidationError(
                f"theta {tuple(theta.shape)} has batch shape {tuple(batch)}, which does not "
                f"broadcast to the model's batch shape {tuple(self.batch_shape)}: give "
                f"({self.n_params},) for every member or (*batch_shape, {self.n_params}), or "
                "build the model with batch_shape= the batch of theta."
            )
        for letter, i, p in self._blocks():
            p.copy_(parts[letter][max(i, 0)].expand_as(p))

    # ------------------------------------------------------------------ polynomials
    def _polys(self, theta: torch.Tensor | None):
        """Padded polynomials: A, C, D ``(*b, n+1)``; B ``(*b, nu, nbk)`` incl. delay; F."""
        co = self._coefficients(theta)
        A, C, D = (_monic(co[k][0]) for k in "acd")
        width = max(k + n for k, n in zip(self.nk, self.nb, strict=True))
        B = torch.stack(
            [F.pad(b, (k, width - k - b.shape[-1])) for b, k in zip(co["b"], self.nk, strict=True)],
            dim=-2,
        )
        nf = max(self.nf)
        Fp = torch.stack([_monic(F.pad(f, (0, nf - f.shape[-1]))) for f in co["f"]], dim=-2)
        return A, B, C, D, Fp

    def _transfer_polys(self, theta: torch.Tensor | None):
        """Numerators ``q^-nk_i B_i`` (``(*b, nu, width)``, delay included) and denominator
        tails of ``A F_i`` without the leading 1 (``(*b, nu, na + max nf)``) of the inputs'
        transfer functions: the few autograd nodes that :meth:`simulate` needs (for an OE
        model the denominator tail is a view of ``theta``)."""
        co = self._coefficients(theta)
        width = max(k + n for k, n in zip(self.nk, self.nb, strict=True))
        nf = max(self.nf)
        B = [F.pad(b, (k, width - k - b.shape[-1])) for b, k in zip(co["b"], self.nk, strict=True)]
        tails = [f if f.shape[-1] == nf else F.pad(f, (0, nf - f.shape[-1])) for f in co["f"]]
        if self.n_inputs == 1:
            B, tails = B[0].unsqueeze(-2), tails[0].unsqueeze(-2)
        else:
            B, tails = torch.stack(B, dim=-2), torch.stack(tails, dim=-2)
        if self.na:
            tails = poly_mul(_monic(co["a"][0]).unsqueeze(-2), _monic(tails))[..., 1:]
        return B, tails

    # ------------------------------------------------------------------ evaluation
    def _inputs(self, u) -> list[torch.Tensor]:
        """List (per experiment) of ``(*batch, nu, N)`` input tensors."""
        if isinstance(u, IOData):
            parts = [p.u for p in u.experiment_list]
        else:
            parts = [as_signal(u, "u", dtype=self.a.dtype, device=self.a.device)]
        for p in parts:
            if p.shape[-1] != self.n_inputs:
                raise InputValidationError(
                    f"u has {p.shape[-1]} channels but the model has {self.n_inputs} inputs."
                )
        return [p.to(self.a.dtype).transpose(-1, -2) for p in parts]

    def _check_data(self, data) -> IOData:
        if not isinstance(data, IOData):
            raise InputValidationError(f"expected IOData, got {type(data).__name__}.")
        if data.ny != 1:
            raise InputValidationError(f"only single-output data (ny = 1); got ny = {data.ny}.")
        if data.nu != self.n_inputs:
            raise InputValidationError(
                f"data has {data.nu} inputs but the model has {self.n_inputs}."
            )
        return data

    def simulate(self, u, zi: torch.Tensor | None = None, theta=None) -> torch.Tensor:
        """Noise-free free run ``y = sum_i q^-nk_i B_i / (A F_i) u_i`` (eq. 4.94 form).

        Args:
            u: ``(*batch, N, nu)`` / ``(N, nu)`` / ``(N,)`` tensor, or :class:`IOData`
                (several experiments are simulated separately and concatenated in time).
            zi: optional ``(*batch, nu, k)`` initial states of the filters
                ``q^-nk_i B_i/(A F_i)`` in scipy.signal.lfilter's convention (single experiment),
                ``k = max(na + max nf, max(nk + nb) - 1)``.
            theta: optional parameter vector used instead of the module's parameters.

        Returns:
            ``(*batch, N, 1)``.
        """
        B, den_tail = self._transfer_polys(theta)  # (*b, nu, .): B_i, tail of A F_i
        parts = self._inputs(u)
        if zi is not None and len(parts) > 1:
            raise InputValidationError("zi is only supported for a single experiment.")
        k = max(den_tail.shape[-1], B.shape[-1] - 1)
        if zi is not None and (not isinstance(zi, torch.Tensor) or zi.shape[-1:] != (k,)):
            got = tuple(zi.shape) if isinstance(zi, torch.Tensor) else type(zi).__name__
            raise InputValidationError(
                f"zi must be (*batch, nu, k) with k = max(na + max nf, max(nk + nb) - 1) = {k} "
                "(the state of each input's filter q^-nk B / (A F) in scipy.signal.lfilter's "
                f"convention), got {got}; zi=None starts at rest."
            )
        out = []
        for x in parts:
            y = _sum_inputs(iir_filter(B, den_tail, x, zi))
            out.append(y.unsqueeze(-1))
        return out[0] if len(out) == 1 else torch.cat(out, dim=-2)

    def predict(self, data: IOData, horizon: int | float | None = 1, theta=None):
        """k-step-ahead prediction ``yhat(t | t-k)`` (eq. 4.130 for k = 1), ``(*batch, N, 1)``.

        ``yhat = Hbar_k (D/C) sum_i q^-nk_i B_i/F_i u_i + (C - Hbar_k A D)/C y`` where
        ``Hbar_k`` holds the first ``k`` impulse-response coefficients of ``H = C/(A D)``
        (``Hbar_1 = 1``: eq. 4.130 with ``H^-1 G = D B/(C F)``, ``1 - H^-1 = (C - A D)/C``).
        The y-part uses only ``y_{t-k}, y_{t-k-1}, ...``. ``horizon=math.inf`` or ``None``:
        :meth:`simulate`. Zero initial conditions in each experiment.
        """
        data = self._check_data(data)
        if horizon is None or (not isinstance(horizon, bool) and horizon == math.inf):
            return self.simulate(data, theta=theta)
        if not _is_integer(horizon) or horizon < 1:
            raise InputValidationError(
                f"horizon must be an integer >= 1 (samples ahead) or math.inf / None (free-run "
                f"simulation), got {horizon!r}."
            )
        k = int(horizon)
        A, B, C, D, Fp = self._polys(theta)
        AD = poly_mul(A, D)
        if k > 1:
            impulse = F.pad(torch.ones_like(C[..., :1]), (0, k - 1))
            Hk = iir_filter(C, AD[..., 1:], impulse)  # first k terms of C/(AD)
        else:
            Hk = torch.ones_like(C[..., :1])
        u_num = poly_mul(poly_mul(Hk, D).unsqueeze(-2), B)  # (*b, nu, .)
        u_den = poly_mul(C.unsqueeze(-2), Fp)
        HkAD = poly_mul(Hk, AD)
        width = max(C.shape[-1], HkAD.shape[-1])
        y_num = F.pad(C, (0, width - C.shape[-1])) - F.pad(HkAD, (0, width - HkAD.shape[-1]))
        y_num = F.pad(y_num[..., k:], (k, 0))  # exactly zero up to lag k - 1
        out = []
        for part in data.experiment_list:
            x = part.u.to(A.dtype).transpose(-1, -2)
            y = part.y.to(A.dtype)[..., 0]
            yhat = _sum_inputs(iir_filter(u_num, u_den[..., 1:], x))
            if self.na + self.nc + self.nd > 0:  # H = 1 (output error): no y-part
                yhat = yhat + iir_filter(y_num, C[..., 1:], y)
            out.append(yhat.unsqueeze(-1))
        return out[0] if len(out) == 1 else torch.cat(out, dim=-2)

    def prediction_errors(self, data: IOData, horizon=1, theta=None) -> torch.Tensor:
        """``y - predict(data, horizon)``, ``(*batch, N, 1)``."""
        return data.y - self.predict(data, horizon=horizon, theta=theta)

    def simulation_errors(self, data: IOData, theta=None) -> torch.Tensor:
        """``y - simulate(data)``, ``(*batch, N, 1)``."""
        data = self._check_data(data)
        return data.y - self.simulate(data, theta=theta)

    def forward(self, data: IOData, horizon=1) -> torch.Tensor:
        """Same as :meth:`predict`."""
        return self.predict(data, horizon=horizon)

    # ------------------------------------------------------------------ analysis
    def poles(self) -> torch.Tensor:
        """Poles of G and H: roots of A, D and every F_i, ``(*batch, na + nd + sum nf)``."""
        with torch.no_grad():
            parts = [self.a, self.d, *self.f]
            return torch.cat([_roots(p) for p in parts], dim=-1)

    def zeros(self, input: int = 0) -> torch.Tensor:
        """Zeros of ``B_input`` (roots of ``b1 z^(nb-1) + ... + b_nb``), ``(*batch, nb - 1)``.

        Assumes ``b1 != 0`` (a leading zero means a longer delay: raise nk instead).
        """
        if not _is_integer(input) or not 0 <= input < self.n_inputs:
            raise InputValidationError(
                f"input must be the index of an input, an integer in [0, {self.n_inputs - 1}] "
                f"(this model has {self.n_inputs} input(s)), got {input!r}."
            )
        with torch.no_grad():
            b = self.b[input]
            if b.shape[-1] <= 1:
                return torch.zeros(*self.batch_shape, 0, dtype=torch.complex128)
            return _roots(b[..., 1:] / b[..., :1])

    def is_stable(self) -> torch.Tensor:
        """``(*batch,)`` bool: every pole of G and H strictly inside the unit circle."""
        p = self.poles()
        return (p.abs() < 1).all(dim=-1)

    @torch.no_grad()
    def stabilize(self) -> torch.Tensor:
        """Reflect roots of F_i, C, D outside the unit circle to ``1 / conj(r)`` (in place).

        Keeps output-error and Box-Jenkins iterations on stable predictors (C, D: the noise
        spectrum is unchanged up to a scale; F: the nearest stable model). Returns
        ``(*batch,)`` bool: whether anything was changed.
        """
        changed = torch.zeros(self.batch_shape, dtype=torch.bool, device=self.a.device)
        for p in [self.c, self.d, *self.f]:
            if p.shape[-1] == 0:
                continue
            r = _roots(p)
            outside = r.abs() > 1
            if bool(outside.any()):
                r = torch.where(outside, 1 / r.conj(), r)
                p.copy_(_monic_from_roots(r).to(p.dtype))
                changed |= outside.any(-1)
        return changed

    def frequency_response(self, omega, noise: bool = False) -> torch.Tensor:
        """``G(e^{j omega Ts})`` (``(*batch, n_omega, nu)``) or ``H`` (``(*batch, n_omega)``).

        Args:
            omega: angular frequencies in rad/s (``(n_omega,)``).
        """
        omega = torch.as_tensor(omega, dtype=torch.float64, device=self.a.device).reshape(-1)
        with torch.no_grad():
            A, B, C, D, Fp = (t.to(torch.complex128) for t in self._polys(None))

            def ev(p):  # p(q^-1) at q = e^{j w Ts}: sum_k p_k e^{-j w Ts k}, (..., n_omega)
                k = torch.arange(p.shape[-1], device=p.device, dtype=torch.float64)
                zk = torch.exp(-1j * omega.unsqueeze(-1) * self.Ts * k)  # (n_omega, n)
                return (p.unsqueeze(-2) * zk).sum(-1)

            if noise:
                return ev(C) / (ev(A) * ev(D))
            return (ev(B) / ev(Fp)).transpose(-1, -2) / ev(A).unsqueeze(-1)

    def __getitem__(self, index) -> PolynomialModel:
        """The model(s) at ``index`` of the batch, as a new (detached) model."""
        if not self.batch_shape:
            raise InputValidationError("this model has no batch dimension to index.")
        index = index if isinstance(index, tuple) else (index,)
        theta = self.parameter_vector().detach()[index]
        new = PolynomialModel(
            self.na,
            self.nb,
            self.nc,
            self.nd,
            self.nf,
            self.nk,
            n_inputs=self.n_inputs,
            batch_shape=theta.shape[:-1],
            dtype=self.a.dtype,
            device=self.a.device,
            Ts=self.Ts,
        )
        new.__class__ = self.__class__
        new.set_parameter_vector(theta)
        return new

    def to_control(self, noise: bool = False):
        """python-control ``TransferFunction`` in z with ``dt = Ts`` (1 output, nu inputs).

        ``noise=True`` gives ``H = C/(A D)``. A batched model gives a flat list (row-major
        over the batch); ``model[i].to_control()`` gives one.
        """
        import control

        with torch.no_grad():
            A, B, C, D, Fp = (t.detach().cpu().double().numpy() for t in self._polys(None))
        flat = int(np.prod(self.batch_shape))
        A, C, D = (x.reshape(flat, -1) for x in (A, C, D))
        B, Fp = (x.reshape(flat, self.n_inputs, -1) for x in (B, Fp))

        def tf_z(num, den):  # q^-1 polynomials -> z polynomials of equal degree
            width = max(len(num), len(den))
            return list(np.pad(num, (0, width - len(num)))), list(
                np.pad(den, (0, width - len(den)))
            )

        systems = []
        for j in range(flat):  # conversion to python objects, one per batch member
            if noise:
                num, den = tf_z(C[j], np.convolve(A[j], D[j]))
                systems.append(control.tf(num, den, dt=self.Ts))
                continue
            nums, dens = [], []
            for i in range(self.n_inputs):
                num, den = tf_z(B[j, i], np.convolve(A[j], Fp[j, i]))
                nums.append(num)
                dens.append(den)
            systems.append(control.tf([nums], [dens], dt=self.Ts))
        return systems[0] if not self.batch_shape else systems

    # ------------------------------------------------------------------ regression
    def _max_lag(self) -> int:
        return max([self.na] + [k + n - 1 for k, n in zip(self.nk, self.nb, strict=True)])

    def _regressor_columns(self) -> list[tuple[int, int, float]]:
        """``(signal, lag, sign)`` of each column of :meth:`regression`'s ``Phi``, signal 0
        being ``y`` and signal ``i + 1`` the input ``u_i``: column ``(s, l, sign)`` holds
        ``sign * signal_s[t - l]`` in the row of sample ``t``."""
        cols = [(0, lag, -1.0) for lag in range(1, self.na + 1)]
        for i, (k, n) in enumerate(zip(self.nk, self.nb, strict=True)):
            cols += [(i + 1, lag, 1.0) for lag in range(k, k + n)]
        return cols

    def _regression_parts(self, data: IOData) -> tuple[IOData, int, list[list[torch.Tensor]]]:
        """Checked data, the first regression row ``start`` (the largest lag) and, per
        experiment, the signals of :meth:`_regressor_columns` (``y`` then the inputs, each
        ``(*batch, N)`` with unit stride: a view of single-input data, else a copy)."""
        if not self.is_linear_in_parameters:
            raise InputValidationError(
                f"{type(self).__name__} is not linear in its parameters; regression() exists "
                "for FIR and ARX only."
            )
        data = self._check_data(data)
        start = self._max_lag()
        signals = []
        for e, part in enumerate(data.experiment_list):
            if part.N <= start:
                raise InputValidationError(
                    f"experiment {e} has {part.N} samples but the regressors need {start + 1} "
                    f"(max lag {start}); use a longer experiment or lower orders."
                )
            signals.append([x.contiguous() for x in (part.y[..., 0], *part.u.unbind(-1))])
        return data, start, signals

    def regression(self, data: IOData) -> tuple[torch.Tensor, torch.Tensor]:
        """Linear regression form ``target = Phi theta`` (FIR/ARX only, eq. 4.111).

        Row for sample t (only where every lag is inside the experiment, t >= max lag):
        ``[-y_{t-1}, ..., -y_{t-na}, u1_{t-nk1}, ..., u1_{t-nk1-nb1+1}, u2_..]``,
        target ``y_t``. Experiments are stacked. Returns ``Phi (*batch, M, p)``,
        ``target (*batch, M)``. ``Phi`` is stored column by column (each column one
        contiguous copy of a shifted signal; the column-major layout LAPACK's QR reads
        without a copy).
        """
        data, start, signals = self._regression_parts(data)
        cols = self._regressor_columns()
        M = sum(x[0].shape[-1] - start for x in signals)
        x0 = signals[0][0]
        PhiT = x0.new_empty(*x0.shape[:-1], len(cols), M)
        row = 0
        for x in signals:  # loop over experiments
            N = x[0].shape[-1]
            rows = slice(row, row + N - start)
            for j, (s, lag, sign) in enumerate(cols):  # loop over the p columns
                src = x[s][..., start - lag : N - lag]
                if sign < 0:
                    torch.neg(src, out=PhiT[..., j, rows])
                else:
                    PhiT[..., j, rows].copy_(src)
            row = rows.stop
        target = torch.cat([x[0][..., start:] for x in signals], dim=-1)
        return PhiT.transpose(-1, -2), target

    def normal_equations(self, data: IOData) -> tuple[torch.Tensor, int]:
        """Gram matrix ``Z'Z`` of the augmented regressor ``Z = [Phi, target]`` of
        :meth:`regression` (FIR/ARX), without forming ``Phi``: ``(*batch, p + 1, p + 1)``
        holding ``Phi'Phi``, ``Phi'target`` and ``target'target``, and the number of rows
        ``M``.

        Each entry is a lagged product of two signals summed over the rows ``t >= start``:
        ``sum_t a_{t-l} b_{t-m}``. The sum over every ``t`` where both samples exist (the
        signals' correlation at lag ``m - l``, :func:`sysid.lls._lagged_products`: ``O(N)``
        matmul work per lag, no copy of the signals) minus the rows ``t < start`` and
        ``t >= N`` of the zero-padded regressor (``start`` rows each, built from the first
        and last ``start`` samples) gives it. Experiments add.
        """
        from .lls import _lagged_products  # lls builds on the filters, as this module does

        data, start, signals = self._regression_parts(data)
        cols = [*self._regressor_columns(), (0, 0, 1.0)]
        sign = torch.tensor([c[2] for c in cols], dtype=data.dtype, device=data.device)
        sign = sign.unsqueeze(-1) * sign
        # (w, z) -> largest lag d of sum_m w_m z_{m+d} needed: the pair of columns (i, j)
        # with d = l_j - l_i >= 0 is sum_m s_j[m] s_i[m + d], otherwise sum_m s_i[m] s_j[m - d]
        need: dict[tuple[int, int], int] = {}
        pairs = []
        for i, (si, li, _) in enumerate(cols):
            for j, (sj, lj, _) in enumerate(cols[i:], start=i):
                w, z, d = (sj, si, lj - li) if lj >= li else (si, sj, li - lj)
                need[(w, z)] = max(need.get((w, z), 0), d)
                pairs.append((i, j, w, z, d))
        G = None
        for x in signals:  # loop over experiments
            N = x[0].shape[-1]
            lagged = {(w, z): _lagged_products(x[w], x[z], d + 1) for (w, z), d in need.items()}
            full = torch.stack([lagged[(w, z)][..., d] for _, _, w, z, d in pairs], dim=-1)
            Gx = x[0].new_zeros(*full.shape[:-1], len(cols), len(cols))
            iu = torch.tensor([(i, j) for i, j, *_ in pairs], device=full.device).T
            Gx[..., iu[0], iu[1]] = full
            Gx[..., iu[1], iu[0]] = full
            Gx = Gx * sign
            if start:
                first = [F.pad(s[..., :start], (start, 0)) for s in x]
                last = [F.pad(s[..., N - start :], (0, start)) for s in x]
                head, tail = (self._edge_rows(e, cols, start) for e in (first, last))
                Gx = Gx - head.transpose(-1, -2) @ head - tail.transpose(-1, -2) @ tail
            G = Gx if G is None else G + Gx
        return G, sum(x[0].shape[-1] - start for x in signals)

    @staticmethod
    def _edge_rows(edge: list[torch.Tensor], cols, start: int) -> torch.Tensor:
        """Rows of the zero-padded augmented regressor outside ``[start, N)``,
        ``(*batch, start, p + 1)``: for ``edge`` the first ``start`` samples after ``start``
        zeros, the rows ``t = 0 .. start - 1``; for the last ``start`` samples before
        ``start`` zeros, the rows ``t = N .. N + start - 1`` (``edge``:
        ``(*batch, 2 start)`` per signal; row ``tau``, column ``(s, l, sign)`` holds
        ``sign * edge[s][tau + start - l]`` in both cases)."""
        tau = torch.arange(start, device=edge[0].device)
        out = [sign * edge[s][..., tau + start - lag] for s, lag, sign in cols]
        return torch.stack(out, dim=-1)

    def regression_residuals(self, data: IOData, theta: torch.Tensor) -> torch.Tensor:
        """``target - Phi theta`` of :meth:`regression` (FIR/ARX) for ``theta``
        (``(*batch, p)``), ``(*batch, M)``, without forming ``Phi``: one in-place
        multiply-add of a shifted signal per column of :meth:`_regressor_columns`."""
        data, start, signals = self._regression_parts(data)
        cols = self._regressor_columns()
        signs = torch.tensor([-sign for *_, sign in cols], dtype=theta.dtype, device=theta.device)
        coef = theta * signs
        out = []
        for x in signals:  # loop over experiments
            N = x[0].shape[-1]
            batch = torch.broadcast_shapes(x[0].shape[:-1], coef.shape[:-1])
            r = x[0][..., start:].expand(*batch, N - start).clone()
            for j, (s, lag, _) in enumerate(cols):  # loop over the p columns
                r.addcmul_(coef[..., j : j + 1], x[s][..., start - lag : N - lag])
            out.append(r)
        return out[0] if len(out) == 1 else torch.cat(out, dim=-1)

    def extra_repr(self) -> str:
        orders = f"na={self.na}, nb={self.nb}, nc={self.nc}, nd={self.nd}, nf={self.nf}"
        return f"{orders}, nk={self.nk}, batch_shape={tuple(self.batch_shape)}, Ts={self.Ts}"


_COMMON = dict(n_inputs=1, batch_shape=(), dtype=torch.float64, device=None, Ts=DEFAULT_TS)

_ORDER_MEANING = {
    "na": "the number of coefficients a1..a_na of A",
    "nb": "the number of coefficients b1..b_nb of B (per input)",
    "nc": "the number of coefficients c1..c_nc of C",
    "nd": "the number of coefficients d1..d_nd of D",
    "nf": "the number of coefficients f1..f_nf of F (per input)",
}


def _require_polynomials(model: PolynomialModel, names: str) -> None:
    """Raise unless every order in ``names`` (e.g. ``"nb nf"``) is >= 1 (for every input):
    a named structure needs each of its polynomials (a zero order drops one, e.g. OE with
    nf = 0 is FIR, nb = 0 leaves an input unused)."""
    structure = type(model).__name__
    for name in names.split():
        value = getattr(model, name)
        if min(value if isinstance(value, list) else [value]) < 1:
            orders = ", ".join(names.split())
            raise InputValidationError(
                f"{structure}: {name} = {value} but {structure} needs {name} >= 1 "
                f"({name} is {_ORDER_MEANING[name]}). Orders count coefficients as in MATLAB "
                f"({orders}: numbers of coefficients, nk: input delay in samples); "
                f"{structure} needs each of {orders} >= 1. For a structure without that "
                "polynomial use FIR, ARX, OE, ARMAX or the general PolynomialModel."
            )


class FIR(PolynomialModel):
    """Finite impulse response ``y_t = B(q) u(t - nk) + e_t`` (eq. 4.96 / 4.114).

    ``nb`` = number of b-coefficients, ``nk`` = input delay (MATLAB ``arx(data,[0 nb nk])``).
    """

    is_linear_in_parameters = True

    def __init__(self, nb, nk=1, **kwargs):
        super().__init__(nb=nb, nk=nk, **{**_COMMON, **kwargs})
        _require_polynomials(self, "nb")


class ARX(PolynomialModel):
    """``A(q) y_t = B(q) u(t - nk) + e_t`` (eq. 4.117-4.120, MATLAB signs).

    ``na`` = number of a-coefficients, ``nb`` = number of b-coefficients, ``nk`` = delay.
    Either may be zero (``nb = 0``: an AR model of a time series; ``na = 0``: FIR), not both.
    """

    is_linear_in_parameters = True

    def __init__(self, na, nb, nk=1, **kwargs):
        super().__init__(na=na, nb=nb, nk=nk, **{**_COMMON, **kwargs})
        if self.na + sum(self.nb if isinstance(self.nb, list) else [self.nb]) < 1:
            raise InputValidationError(
                f"ARX: na = {self.na} and nb = {self.nb} leave no coefficient to estimate "
                f"(na is {_ORDER_MEANING['na']}, nb {_ORDER_MEANING['nb']}; nk is the input "
                "delay in samples, the number of coefficients as in MATLAB): give na >= 1 "
                "or nb >= 1."
            )


class OE(PolynomialModel):
    """Output error ``y_t = B(q)/F(q) u(t - nk) + e_t`` (H = 1: predict == simulate, 4.133).

    ``nb``/``nf`` = numbers of b-/f-coefficients, ``nk`` = delay (MATLAB ``oe(data,[nb nf nk])``).
    """

    def __init__(self, nb, nf, nk=1, **kwargs):
        super().__init__(nb=nb, nf=nf, nk=nk, **{**_COMMON, **kwargs})
        _require_polynomials(self, "nb nf")


class ARMAX(PolynomialModel):
    """``A(q) y_t = B(q) u(t - nk) + C(q) e_t`` (MATLAB ``armax(data,[na nb nc nk])``)."""

    def __init__(self, na, nb, nc, nk=1, **kwargs):
        super().__init__(na=na, nb=nb, nc=nc, nk=nk, **{**_COMMON, **kwargs})
        _require_polynomials(self, "na nb nc")


class BJ(PolynomialModel):
    """Box-Jenkins ``y_t = B/F u(t - nk) + C/D e_t`` (eq. 4.121).

    MATLAB ``bj(data, [nb nc nd nf nk])``; orders count coefficients, ``nk`` is the delay.
    """

    def __init__(self, nb, nc, nd, nf, nk=1, **kwargs):
        super().__init__(nb=nb, nc=nc, nd=nd, nf=nf, nk=nk, **{**_COMMON, **kwargs})
        _require_polynomials(self, "nb nc nd nf")
