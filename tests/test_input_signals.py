"""Excitation signals of :func:`sysid.montecarlo.input_signal` against their definitions: the
maximum-length sequence (period, two-valued periodic autocorrelation, balance) and the
random-phase multisine (DFT lines only in the band, flat amplitude, RMS); the argument checks
of the module's generators (input_signal, simulate_data)."""

import math

import numpy as np
import pytest
import torch

from integrators.errors import InputValidationError
from sysid.models import OE
from sysid.montecarlo import MLS_TAPS, input_signal, simulate_data


@pytest.mark.parametrize("order", [n for n in MLS_TAPS if n <= 14])
def test_mls_is_a_maximum_length_sequence(order):
    """Period exactly 2^n - 1 (not a divisor of it), 2^(n-1) levels +1 and one fewer -1, and
    periodic autocorrelation 1 at lag 0 and -1/P at every other lag (by numpy's FFT)."""
    P = 2**order - 1
    u = input_signal("mls", 2 * P, order=order, seed=order)[:, 0].numpy()
    assert np.array_equal(u[:P], u[P:])
    assert all(not np.array_equal(u[:P], np.roll(u[:P], d)) for d in range(1, P) if P % d == 0)
    assert u[:P].sum() == 1.0
    spectrum = np.fft.fft(u[:P])
    autocorrelation = np.fft.ifft(spectrum * spectrum.conj()).real / P
    np.testing.assert_allclose(autocorrelation[0], 1.0, atol=1e-12)
    np.testing.assert_allclose(autocorrelation[1:], -1.0 / P, atol=1e-12)


def test_mls_holds_levels_shifts_per_data_set_and_covers_the_record():
    """Each level is held ``hold`` samples; every data set and channel is a circular shift of
    one sequence (the same seed reproduces them); the default order is the shortest whose
    period covers N (N = 100, hold = 3: 34 levels, order 6)."""
    u = input_signal("mls", 100, (3,), n_inputs=2, hold=3, amplitude=2.0, seed=4)
    assert u.shape == (3, 100, 2) and set(u.unique().tolist()) == {-2.0, 2.0}
    levels = u[..., 0::3, :]  # (3, 34, 2)
    assert torch.equal(levels.repeat_interleave(3, dim=-2)[..., :100, :], u)
    reference = input_signal("mls", 63, order=6, seed=0)[:, 0]
    doubled = torch.cat([reference, reference]) * 2.0
    for member in levels.permute(0, 2, 1).reshape(6, 34):
        assert any(torch.equal(member, doubled[s : s + 34]) for s in range(63))
    assert not torch.equal(levels[0, :, 0], levels[1, :, 0])
    assert torch.equal(u, input_signal("mls", 100, (3,), n_inputs=2, hold=3, amplitude=2.0, seed=4))


@pytest.mark.parametrize("N, band", [(200, (0.05, 0.2)), (64, (0.3, 0.5)), (101, (0.0, 0.5))])
def test_multisine_has_flat_lines_only_in_its_band(N, band):
    """Over one period (N samples) the DFT of a random-phase multisine is non-zero exactly at
    the bins k with band[0] < k/N <= band[1], all of one magnitude, and its RMS is the
    amplitude (with a line at the Nyquist frequency, N = 64, whose power depends on its
    phase)."""
    u = input_signal("multisine", N, (2,), amplitude=1.5, band=band, seed=7)[..., 0].numpy()
    for member in u:
        np.testing.assert_allclose(np.sqrt(np.mean(member**2)), 1.5, rtol=1e-12)
        spectrum = np.abs(np.fft.rfft(member))
        k = np.arange(spectrum.size)
        inside = (k / N > band[0]) & (k / N <= band[1])
        assert spectrum[~inside].max() < 1e-9 * spectrum.max()
        interior = inside & (2 * k != N)
        np.testing.assert_allclose(spectrum[interior], spectrum[interior][0], rtol=1e-10)
    assert not np.allclose(u[0], u[1])


def test_float32_signals_keep_their_phase_on_long_records():
    """On a record of 16 384 samples (k j passes 2^24, float32's integer range) the float32
    multisine and sinusoid equal the definitions evaluated in float64 with the same phases
    (float32 draws) to float32 rounding, and the multisine keeps its DFT in the band (leakage below
    -140 dB, float32's floor)."""
    N, band = 16384, (0.1, 0.12)
    u = input_signal("multisine", N, band=band, seed=3, dtype=torch.float32)[:, 0]
    assert u.dtype == torch.float32
    lines = np.array([k for k in range(1, N // 2) if band[0] < k / N <= band[1]])
    generator = torch.Generator().manual_seed(3)
    phase = 2 * np.pi * torch.rand(lines.size, generator=generator).double().numpy()
    angle = 2 * np.pi * ((lines[None, :] * np.arange(N)[:, None]) % N) / N
    exact = np.cos(angle + phase).sum(-1) / np.sqrt(0.5 * lines.size)
    np.testing.assert_allclose(u.double().numpy(), exact, atol=2 * np.finfo(np.float32).eps)
    power = np.abs(np.fft.rfft(u.double().numpy())) ** 2
    k = np.arange(power.size)
    inside = (k / N > band[0]) & (k / N <= band[1])
    assert 10 * np.log10(power[~inside].sum() / power[inside].sum()) < -140.0
    s = input_signal("sinusoid", N, omega=0.3, seed=5, dtype=torch.float32)[:, 0]
    phase = 2 * np.pi * torch.rand(1, generator=torch.Generator().manual_seed(5)).item()
    exact = np.sin(0.3 * np.arange(N) + phase)
    np.testing.assert_allclose(s.double().numpy(), exact, atol=np.finfo(np.float32).eps)


def test_bad_signal_options_are_named():
    with pytest.raises(InputValidationError, match="order"):
        input_signal("mls", 10, order=40)
    with pytest.raises(InputValidationError, match="band"):
        input_signal("multisine", 10, band=(0.3, 0.2))
    with pytest.raises(InputValidationError, match="no frequency"):
        input_signal("multisine", 8, band=(0.01, 0.1))
    with pytest.raises(InputValidationError, match="period"):
        input_signal("multisine", 10, period=1)


@pytest.mark.parametrize(
    "noise_std", [math.nan, -1.0, math.inf, True, "0.1", torch.tensor([0.1, 0.2])]
)
def test_simulate_data_refuses_a_noise_std_that_is_not_a_finite_number_ge_0(noise_std):
    """An `if noise_std > 0` guard skipped the noise for NaN and -1 and returned noise-free
    data as if they had been asked for."""
    u = input_signal("white", 20, seed=1)
    with pytest.raises(InputValidationError, match="noise_std .* finite real number >= 0"):
        simulate_data(OE(1, 1, 1), u, noise_std=noise_std)


def test_simulate_data_noise_std_forms():
    """noise_std 0 gives G u exactly; a numpy float and a 0-d tensor add std * N(0, 1) drawn
    from the generator (the same draws as torch.randn with that seed)."""
    model = OE(1, 1, 1)
    model.set_parameter_vector(torch.tensor([0.5, -0.8], dtype=torch.float64))
    u = input_signal("white", 30, (2,), seed=1)
    clean = model.simulate(u).detach()
    assert torch.equal(simulate_data(model, u, noise_std=0).y, clean)
    draws = torch.randn((2, 30), generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    for std in (np.float64(0.5), torch.tensor(0.5)):
        y = simulate_data(model, u, noise_std=std, seed=7).y
        torch.testing.assert_close(y[..., 0] - clean[..., 0], 0.5 * draws, rtol=0, atol=1e-14)


@pytest.mark.parametrize("batch_shape", [-2, (-2,), (3, -1), (2.0,), 1.5, "3", (True,)])
def test_input_signal_refuses_a_batch_shape_that_is_not_integers_ge_0(batch_shape):
    """A negative size raised torch's RuntimeError (negative dimension) from inside."""
    with pytest.raises(InputValidationError, match="batch_shape must be an integer >= 0"):
        input_signal("white", 10, batch_shape)


def test_input_signal_batch_shape_forms():
    """An integer, a tuple, numpy integers and an empty batch give the shape asked for."""
    assert input_signal("white", 10, 3).shape == (3, 10, 1)
    assert input_signal("prbs", 10, (2, np.int64(3))).shape == (2, 3, 10, 1)
    assert input_signal("white", 10, np.int32(0)).shape == (0, 10, 1)
    assert input_signal("white", 10, ()).shape == (10, 1)
