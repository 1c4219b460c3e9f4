"""Monte-Carlo helpers: batched experiment generation and summaries of estimator statistics.

A Monte-Carlo study is one batched call: :func:`input_signal` draws ``(*batch, N, nu)``
inputs, :func:`simulate_data` runs a known system on them and adds noise (white output noise,
or noise shaped by the model's own noise model ``H = C/(A D)``, e.g. the equation error
``1/A`` of ARX), and :func:`summarize_estimates` compares the spread of the estimates with
the covariance the theory predicts (bias, standard deviation, empirical covariance, relative
Frobenius error, coverage of confidence intervals). All randomness comes from a
``torch.Generator`` (or a seed).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np
import torch

from integrators.errors import InputValidationError

from .data import IOData
from .filters import iir_filter, poly_mul
from .models import PolynomialModel, _batch_shape

__all__ = [
    "INPUT_KINDS",
    "NOISE_KINDS",
    "MonteCarloSummary",
    "fir_regressor",
    "input_signal",
    "noise_signal",
    "simulate_data",
    "summarize_estimates",
]

INPUT_KINDS = ("white", "prbs", "mls", "multisine", "step", "sinusoid")

#: Feedback taps of a maximal-length linear-feedback shift register of each order: the
#: exponents of a primitive polynomial ``x^n + ... + 1`` over GF(2) besides the constant.
MLS_TAPS = {
    2: (2, 1), 3: (3, 2), 4: (4, 3), 5: (5, 3), 6: (6, 5), 7: (7, 6), 8: (8, 6, 5, 4),
    9: (9, 5), 10: (10, 7), 11: (11, 9), 12: (12, 6, 4, 1), 13: (13, 4, 3, 1),
    14: (14, 5, 3, 1), 15: (15, 14), 16: (16, 15, 13, 4), 17: (17, 14), 18: (18, 11),
    19: (19, 6, 2, 1), 20: (20, 17),
}  # fmt: skip
NOISE_KINDS = ("gaussian", "student_t", "laplace", "uniform", "contaminated")


def _generator(generator, seed, device) -> torch.Generator:
    """``generator``; else a new one seeded with ``seed``; else with fresh entropy from the
    operating system (a fixed default would give every call the same draws: noise equal to
    an input drawn the same way, Monte-Carlo trials that repeat one trial)."""
    if generator is not None:
        return generator
    g = torch.Generator(device=device if device is not None else "cpu")
    if seed is None:
        g.seed()
    else:
        g.manual_seed(int(seed))
    return g


def _check_float_dtype(dtype) -> None:
    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise InputValidationError(
            f"dtype must be a real floating torch dtype (e.g. torch.float64), got {dtype}."
        )


def input_signal(
    kind: str,
    N: int,
    batch_shape=(),
    *,
    n_inputs: int = 1,
    amplitude: float = 1.0,
    omega: float = 0.3,
    hold: int = 1,
    order: int | None = None,
    band: tuple[float, float] = (0.0, 0.5),
    period: int | None = None,
    generator: torch.Generator | None = None,
    seed: int | None = None,
    dtype=torch.float64,
    device=None,
) -> torch.Tensor:
    """Excitation signals of shape ``(*batch_shape, N, n_inputs)``.

    Args:
        kind: ``"white"`` (Gaussian, standard deviation ``amplitude``), ``"prbs"`` (random
            binary ``+-amplitude``, each level held ``hold`` samples: a pseudo-random binary
            signal whose spectrum is white for ``hold = 1``), ``"mls"`` (a maximum-length
            binary sequence ``+-amplitude``, MATLAB's ``idinput(..., 'prbs')``: the output of a
            shift register of ``order`` bits with primitive feedback, period ``2^order - 1``
            levels, each held ``hold`` samples, its periodic autocorrelation ``1`` at lag 0 and
            ``-1 / (2^order - 1)`` elsewhere (``hold = 1``); a random circular shift per data
            set and channel), ``"multisine"`` (``sum_k cos(2 pi k j / period + phi_k)`` over
            the integers ``k`` with ``band[0] < k / period <= band[1]`` (frequencies in cycles
            per sample, at most 0.5), random phases ``phi_k`` per data set and channel, scaled
            to RMS ``amplitude`` over a period), ``"step"`` (``amplitude`` from sample 0 on,
            system at rest before) or ``"sinusoid"`` (``amplitude sin(omega k + phase)`` with a
            random phase per data set).
        N: number of samples (an integer >= 1).
        batch_shape: leading batch shape (one signal per data set), an integer >= 0 or a
            sequence of them.
        n_inputs: number of input channels (an integer >= 1).
        hold: samples per PRBS / MLS level (an integer >= 1).
        order: MLS register length, 2 to 20 (default: the shortest whose period of
            ``(2^order - 1) hold`` samples covers ``N``).
        band: multisine frequency band ``(low, high)`` in cycles per sample,
            ``0 <= low < high <= 0.5``; period: multisine period in samples (default ``N``:
            the record holds one whole period, so its DFT has lines only in the band).
        dtype: a floating dtype.
        omega: sinusoid frequency in rad/sample.
        generator, seed: randomness (a generator wins over a seed; neither: fresh entropy,
            different draws on every call).
    """
    if kind not in INPUT_KINDS:
        raise InputValidationError(f"kind must be one of {INPUT_KINDS}, got {kind!r}.")
    for name, value in (("N", N), ("hold", hold), ("n_inputs", n_inputs)):
        if not isinstance(value, numbers.Integral) or value < 1:
            raise InputValidationError(f"{name} must be an integer >= 1, got {value!r}.")
    _check_float_dtype(dtype)
    batch_shape = _batch_shape(batch_shape, "data sets")
    shape = (*batch_shape, N, n_inputs)
    g = _generator(generator, seed, device)
    to = dict(dtype=dtype, device=device)
    if kind == "white":
        return torch.randn(shape, generator=g, **to).mul_(amplitude)
    if kind == "prbs":
        n_levels = -(-N // hold)
        levels = torch.randint(0, 2, (*batch_shape, n_levels, n_inputs), generator=g, device=device)
        levels = (2 * levels - 1).to(dtype)
        return amplitude * levels.repeat_interleave(hold, dim=-2)[..., :N, :]
    if kind == "mls":
        return amplitude * _mls(N, hold, order, batch_shape, n_inputs, g, dtype, device)
    if kind == "multisine":
        return amplitude * _multisine(N, band, period, batch_shape, n_inputs, g, dtype, device)
    if kind == "step":
        return torch.full(shape, float(amplitude), **to)
    # the angle in float64: omega k in float32 loses the phase on long records
    phase = 2 * math.pi * torch.rand((*batch_shape, 1, n_inputs), generator=g, **to).double()
    k = torch.arange(N, dtype=torch.float64, device=device).reshape(N, 1)
    return amplitude * torch.sin(omega * k + phase).to(dtype)


def _mls(N, hold, order, batch_shape, n_inputs, g, dtype, device) -> torch.Tensor:
    """``(*batch_shape, N, n_inputs)`` maximum-length sequences of +-1 (see
    :func:`input_signal`)."""
    levels = -(-N // hold)
    if order is None:
        order = next((n for n in MLS_TAPS if 2**n - 1 >= levels), max(MLS_TAPS))
    if order not in MLS_TAPS:
        raise InputValidationError(
            f"order must be an integer from {min(MLS_TAPS)} to {max(MLS_TAPS)}, got {order!r}."
        )
    P = 2**order - 1
    bits = [1] * order  # any non-zero register state starts the period
    for k in range(P - order):
        bits.append(sum(bits[k + order - tap] for tap in MLS_TAPS[order]) % 2)
    sequence = torch.tensor(bits, dtype=dtype, device=device) * 2 - 1  # (P,)
    shift = torch.randint(0, P, (*batch_shape, 1, n_inputs), generator=g, device=device)
    index = (torch.arange(levels, device=device).reshape(levels, 1) + shift) % P
    return sequence[index].repeat_interleave(hold, dim=-2)[..., :N, :]


def _multisine(N, band, period, batch_shape, n_inputs, g, dtype, device) -> torch.Tensor:
    """``(*batch_shape, N, n_inputs)`` random-phase multisines of RMS 1 (see
    :func:`input_signal`)."""
    P = N if period is None else period
    if not isinstance(P, numbers.Integral) or P < 2:
        raise InputValidationError(f"period must be an integer >= 2, got {period!r}.")
    low, high = (float(f) for f in band)
    if not 0.0 <= low < high <= 0.5:
        raise InputValidationError(
            f"band must be (low, high) in cycles per sample with 0 <= low < high <= 0.5, got "
            f"{band!r}."
        )
    lines = [k for k in range(1, P // 2 + 1) if low < k / P <= high]
    if not lines:
        raise InputValidationError(
            f"no frequency k / period (k = 1, 2, ...) of period {P} lies in the band {band!r}; "
            "widen the band or lengthen the period."
        )
    k = torch.tensor(lines, device=device)  # (K,) int64
    phase = 2 * math.pi * torch.rand((*batch_shape, 1, n_inputs, len(lines)), generator=g,
                                     dtype=dtype, device=device).double()  # fmt: skip
    j = torch.arange(N, device=device).reshape(N, 1, 1)
    # the angle in float64 from the exact integer k j mod P (k j passes 2^24, float32's
    # integer range, on records of a few thousand samples)
    angle = 2 * math.pi * ((k * j) % P).double() / P
    # a line at the Nyquist frequency (k = P / 2) has power cos^2(phi), the others 1/2
    power = torch.where(2 * k == P, torch.cos(phase) ** 2, 0.5).sum(-1)
    return (torch.cos(angle + phase).sum(-1) / power.sqrt()).to(dtype)


def noise_signal(
    shape,
    kind: str = "gaussian",
    *,
    std: float = 1.0,
    df: int = 3,
    contamination: float = 0.1,
    outlier_scale: float = 10.0,
    generator: torch.Generator | None = None,
    seed: int | None = None,
    dtype=torch.float64,
    device=None,
) -> torch.Tensor:
    """I.i.d. zero-mean noise with standard deviation ``std`` (scale for heavy tails).

    Args:
        kind: ``"gaussian"``; ``"student_t"`` (``df`` integer degrees of freedom, scaled to
            ``std`` when ``df > 2``); ``"laplace"``; ``"uniform"`` on ``[-a, a]`` with
            ``a = sqrt(3) std``; ``"contaminated"``: Gaussian with probability
            ``1 - contamination`` and Gaussian ``outlier_scale`` times wider otherwise
            (scaled so the inlier standard deviation is ``std``).
        std: finite and >= 0.
        contamination: outlier probability in ``[0, 1]``.
        dtype: a floating dtype.

    Returns:
        noise of shape ``shape``.
    """
    if kind not in NOISE_KINDS:
        raise InputValidationError(f"noise kind must be one of {NOISE_KINDS}, got {kind!r}.")
    if not 0 <= std < math.inf:
        raise InputValidationError(f"std must be finite and >= 0, got {std}.")
    if not 0 <= contamination <= 1:
        raise InputValidationError(
            f"contamination is the probability of an outlier and must lie in [0, 1], "
            f"got {contamination}."
        )
    _check_float_dtype(dtype)
    g = _generator(generator, seed, device)
    to = dict(dtype=dtype, device=device)
    shape = tuple(shape)
    if kind == "gaussian":
        return torch.randn(shape, generator=g, **to).mul_(std)
    if kind == "student_t":
        if int(df) != df or df < 1:
            raise InputValidationError(f"df must be a positive integer, got {df}.")
        z = torch.randn(shape, generator=g, **to)
        chi2 = (torch.randn((*shape, int(df)), generator=g, **to) ** 2).sum(-1)
        t = z / torch.sqrt(chi2 / df)
        return std * t * (math.sqrt((df - 2) / df) if df > 2 else 1.0)
    if kind == "laplace":
        v = torch.rand(shape, generator=g, **to) - 0.5
        e = -torch.sign(v) * torch.log1p(-2 * v.abs())
        return std * e / math.sqrt(2.0)
    if kind == "uniform":
        return std * math.sqrt(3.0) * (2 * torch.rand(shape, generator=g, **to) - 1)
    outlier = torch.rand(shape, generator=g, **to) < contamination
    z = torch.randn(shape, generator=g, **to)
    return std * torch.where(outlier, outlier_scale * z, z)


def fir_regressor(u: torch.Tensor, nb: int, nk: int = 0) -> torch.Tensor:
    """FIR regressor ``U`` of eq. 4.8 from rest: ``U[k, i] = u_{k - nk - i}`` (0 for negative
    times), shape ``(*batch, N, nb)`` for ``u`` of shape ``(*batch, N)``.

    Unlike :meth:`sysid.FIR.regression`, which keeps only the rows whose lags are all inside
    the record, this uses every sample and the knowledge that the system was at rest before
    sample 0 (as in :func:`simulate_data`), as the notes do for Fig. 4.1.

    Args:
        u: inputs ``(*batch, N)``.
        nb: number of taps (an integer >= 1); nk: input delay (an integer >= 0).
    """
    if not isinstance(nb, numbers.Integral) or nb < 1:
        raise InputValidationError(f"fir_regressor: nb must be an integer >= 1, got {nb!r}.")
    if not isinstance(nk, numbers.Integral) or nk < 0:
        raise InputValidationError(
            f"fir_regressor: the delay nk must be an integer >= 0, got {nk!r}."
        )
    padded = torch.nn.functional.pad(u, (nb - 1 + nk, 0))[..., : u.shape[-1] + nb - 1]
    return padded.unfold(-1, nb, 1).flip(-1)


def _noise_polynomials(model: PolynomialModel, theta: torch.Tensor):
    """Numerator ``C`` and denominator tail of ``A D`` for ``H = C / (A D)``."""
    names = model.parameter_names()

    def monic(letter):
        idx = [j for j, n in enumerate(names) if n[0] == letter]
        one = torch.ones(*theta.shape[:-1], 1, dtype=theta.dtype, device=theta.device)
        return torch.cat([one, theta[..., idx]], dim=-1)

    AD = poly_mul(monic("a"), monic("d"))
    return monic("c"), AD[..., 1:]


def simulate_data(
    model: PolynomialModel,
    u: torch.Tensor,
    *,
    noise_std: float = 0.0,
    noise: str = "output",
    noise_kind: str = "gaussian",
    theta: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
    seed: int | None = None,
    Ts: float | None = None,
    **noise_options,
) -> IOData:
    """Data sets of a known system: ``y = G u + v`` with ``v = e`` or ``v = H e``.

    The simulation and the noise are computed in the model's dtype (``u`` and ``theta`` are
    cast to it, as :meth:`PolynomialModel.simulate` casts ``u``); the returned data hold
    ``u`` and ``y`` in the wider of the dtypes of ``u`` and the model (see :class:`IOData`).

    Args:
        model: the true system (its parameters, or ``theta``).
        u: inputs ``(*batch, N, nu)``.
        noise_std: standard deviation of the white noise ``e`` (output units), one finite
            number >= 0 (0: noise-free data).
        noise: ``"output"`` (``v = e``: white measurement noise, the OE assumption) or
            ``"model"`` (``v = C/(A D) e``: the model's own noise model; for ARX the equation
            error ``A y = B u + e``, eq. 4.117–4.120).
        noise_kind: distribution of ``e`` (see :func:`noise_signal`).
        theta: true parameters ``(*batch, p)`` or ``(p,)`` (default: the model's).
        generator, seed: randomness of ``e`` (as in :func:`input_signal`).
        Ts: sample time of the data (default: the model's).
        **noise_options: passed to :func:`noise_signal` (``df``, ``contamination``, ...).

    Returns:
        :class:`IOData` with the broadcast batch shape.
    """
    if noise not in ("output", "model"):
        raise InputValidationError(f"noise must be 'output' or 'model', got {noise!r}.")
    _check_noise_std(noise_std)
    # the simulation runs in the model's dtype, as model.simulate treats u
    th = model.parameter_vector().detach() if theta is None else torch.as_tensor(theta)
    th = th.to(dtype=model.a.dtype, device=model.a.device)
    y = model.simulate(u, theta=th)
    if noise_std > 0:
        e = noise_signal(
            y.shape[:-1],
            noise_kind,
            std=noise_std,
            generator=_generator(generator, seed, u.device),
            dtype=y.dtype,
            device=y.device,
            **noise_options,
        )
        if noise == "model":
            C, AD = _noise_polynomials(model, th)
            e = iir_filter(C, AD, e)
        y = y + e.unsqueeze(-1)
    return IOData(u, y, model.Ts if Ts is None else Ts)


def _check_noise_std(noise_std) -> None:
    """Raise unless ``noise_std`` is one real number, finite and >= 0."""
    scalar = not isinstance(noise_std, bool) and (
        isinstance(noise_std, numbers.Real)
        or (isinstance(noise_std, torch.Tensor) and noise_std.dim() == 0)
    )
    if not scalar or not 0 <= float(noise_std) < math.inf:
        raise InputValidationError(
            f"noise_std (the standard deviation of the white noise e, output units) must be "
            f"one finite real number >= 0, got {noise_std!r}; noise_std=0 gives noise-free "
            "data. For different noise levels per data set, simulate them separately."
        )


@dataclass
class MonteCarloSummary:
    """Statistics of ``T`` estimates of a ``p``-vector (see :func:`summarize_estimates`).

    Attributes:
        mean, bias, std: ``(p,)``; ``bias = mean - truth``; ``std`` the sample standard
            deviation.
        bias_standard_error: ``std / sqrt(T)`` (is the bias significant?), ``(p,)``.
        covariance: sample covariance about the mean, ``(p, p)``.
        mse: mean squared error ``E ||theta_hat - truth||^2`` (scalar tensor).
        predicted_covariance: the theoretical covariance passed in, or None.
        relative_frobenius_error: ``||cov - predicted||_F / ||predicted||_F`` or None.
        coverage: fraction of trials whose truth lies within ``k`` standard errors in every
            parameter (when standard errors were given), or None.
        n_trials: ``T``.
    """

    mean: torch.Tensor
    bias: torch.Tensor
    std: torch.Tensor
    bias_standard_error: torch.Tensor
    covariance: torch.Tensor
    mse: torch.Tensor
    n_trials: int
    predicted_covariance: torch.Tensor | None = None
    relative_frobenius_error: torch.Tensor | None = None
    coverage: torch.Tensor | None = None


def summarize_estimates(
    estimates: torch.Tensor | np.ndarray,
    truth: torch.Tensor,
    predicted_covariance: torch.Tensor | None = None,
    standard_errors: torch.Tensor | None = None,
    k: float = 3.0,
) -> MonteCarloSummary:
    """Bias, spread and covariance of Monte-Carlo estimates against theory.

    Args:
        estimates: ``(*trials, p)`` (all leading dimensions are trials); a tensor or a
            numpy array (as are the other array arguments).
        truth: ``(p,)``.
        predicted_covariance: e.g. ``sigma^2 (U'U)^{-1}`` (eq. 4.101), ``(p, p)``.
        standard_errors: per-trial standard errors ``(*trials, p)`` for the coverage (or a
            shape that broadcasts to it, e.g. ``(p,)`` shared by all trials).
        k: half-width of the coverage interval in standard errors.
    """
    estimates = torch.as_tensor(estimates).detach()
    if estimates.dim() < 1:
        raise InputValidationError("estimates must be (*trials, p), got a 0-d tensor.")
    if not estimates.is_floating_point():
        estimates = estimates.to(torch.get_default_dtype())
    p = estimates.shape[-1]
    est = estimates.reshape(-1, p)
    T = est.shape[0]
    if T < 2:
        raise InputValidationError("need at least 2 trials to summarise estimates.")
    truth = torch.as_tensor(truth, dtype=est.dtype, device=est.device)
    if truth.shape != (p,):
        raise InputValidationError(
            f"truth must have shape (p,) = ({p},) like the last dimension of estimates "
            f"{tuple(estimates.shape)}, got {tuple(truth.shape)}."
        )
    mean = est.mean(0)
    dev = est - mean
    cov = dev.T @ dev / (T - 1)
    std = cov.diagonal().sqrt()
    summary = MonteCarloSummary(
        mean=mean,
        bias=mean - truth,
        std=std,
        bias_standard_error=std / math.sqrt(T),
        covariance=cov,
        mse=((est - truth) ** 2).sum(-1).mean(),
        n_trials=T,
    )
    if predicted_covariance is not None:
        P = torch.as_tensor(predicted_covariance, dtype=est.dtype, device=est.device)
        if P.shape != (p, p):
            raise InputValidationError(
                f"predicted_covariance must have shape (p, p) = ({p}, {p}) for p = {p} "
                f"parameters, got {tuple(P.shape)}."
            )
        summary.predicted_covariance = P
        summary.relative_frobenius_error = torch.linalg.matrix_norm(
            cov - P
        ) / torch.linalg.matrix_norm(P)
    if standard_errors is not None:
        se = torch.as_tensor(standard_errors, dtype=est.dtype, device=est.device).detach()
        try:
            se = se.expand(estimates.shape).reshape(-1, p)
        except RuntimeError:
            raise InputValidationError(
                f"standard_errors must have the shape of estimates {tuple(estimates.shape)} "
                f"(one row per trial, or one row shared by all), got {tuple(se.shape)}."
            ) from None
        summary.coverage = ((est - truth).abs() <= k * se).all(-1).to(est.dtype).mean()
    return summary
