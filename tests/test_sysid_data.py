"""IOData: shapes, validation messages, detrending (vs scipy.signal.detrend), splitting."""

import numpy as np
import pytest
import scipy.signal
import torch

from integrators.errors import InputValidationError
from sysid import IOData


def test_shapes_and_integer_conversion():
    d = IOData(np.arange(10), np.arange(10) * 2, Ts=0.5)
    assert d.u.dtype == torch.float64 and d.u.shape == (10, 1)
    assert (d.N, d.nu, d.ny, d.batch_shape) == (10, 1, 1, torch.Size([]))
    assert torch.equal(d.y[:, 0], 2.0 * torch.arange(10, dtype=torch.float64))
    assert torch.allclose(d.t, 0.5 * torch.arange(10, dtype=torch.float64))


def test_shared_input_broadcasts_against_batched_output():
    u = torch.randn(50, 2, dtype=torch.float64)
    y = torch.randn(7, 50, 1, dtype=torch.float64)
    d = IOData(u, y)
    assert d.batch_shape == (7,) and d.u.shape == (7, 50, 2)
    assert torch.equal(d.u[3], u)
    assert torch.equal(d[2:4].y, y[2:4])


def test_float32_kept_and_mixed_promoted():
    u32 = torch.randn(20, dtype=torch.float32)
    assert IOData(u32, u32).dtype == torch.float32
    assert IOData(u32, u32.double()).dtype == torch.float64
    assert IOData(u32, u32).to(dtype=torch.float64).y.dtype == torch.float64


@pytest.mark.parametrize(
    "u, y, match",
    [
        (np.zeros(10), np.zeros(9), "10 samples but y has 9"),
        (np.zeros(10) + 1j, np.zeros(10), "complex"),
        (torch.zeros(10, dtype=torch.float16), np.zeros(10), "float16"),
        (np.zeros((3, 10, 1)), np.zeros((2, 10, 1)), "do not broadcast"),
        (np.zeros(0), np.zeros(0), "empty"),
        ([np.zeros(10), np.zeros(8)], [np.zeros(10), np.zeros(8)], "IOData.experiments"),
    ],
)
def test_validation_errors(u, y, match):
    with pytest.raises(InputValidationError, match=match):
        IOData(u, y)


def test_bad_sample_time():
    with pytest.raises(InputValidationError, match="Ts"):
        IOData(np.zeros(5), np.zeros(5), Ts=0.0)


def test_non_finite_message_names_sample_batch_and_experiment():
    y = np.zeros((4, 30, 1))
    y[2, 17, 0] = np.nan
    with pytest.raises(InputValidationError, match=r"sample 17, channel 0, batch index \(2,\)"):
        IOData(np.zeros((30, 1)), y)
    u_bad = np.zeros(12)
    u_bad[5] = np.inf
    with pytest.raises(InputValidationError, match="experiment 1.*sample 5|sample 5.*experiment 1"):
        IOData.experiments([(np.zeros(8), np.zeros(8)), (u_bad, np.zeros(12))])


def test_experiments_are_kept_apart_and_checked():
    d1 = IOData(np.arange(5.0), np.ones(5))
    d2 = IOData(np.arange(7.0), np.zeros(7))
    d = IOData.experiments([d1, d2])
    assert d.n_experiments == 2 and d.lengths == [5, 7] and d.N == 12
    assert torch.equal(d.experiment_list[1].u, d2.u)
    with pytest.raises(InputValidationError, match="nu"):
        IOData.experiments([d1, IOData(np.zeros((5, 2)), np.zeros(5))])
    with pytest.raises(InputValidationError, match="Ts"):
        IOData.experiments([d1, IOData(np.zeros(5), np.zeros(5), Ts=2.0)])


@pytest.mark.parametrize("kind, scipy_kind", [("mean", "constant"), ("linear", "linear")])
def test_detrend_matches_scipy_per_experiment(kind, scipy_kind):
    rng = np.random.default_rng(0)
    parts = [
        (rng.normal(size=(3, n, 2)) + 5, rng.normal(size=(3, n, 1)) + np.arange(n)[:, None])
        for n in (40, 25)
    ]
    d = IOData.experiments(parts).detrend(kind)
    for p, (u, y) in zip(d.experiment_list, parts, strict=True):
        np.testing.assert_allclose(
            p.u.numpy(), scipy.signal.detrend(u, axis=-2, type=scipy_kind), atol=1e-12
        )
        np.testing.assert_allclose(
            p.y.numpy(), scipy.signal.detrend(y, axis=-2, type=scipy_kind), atol=1e-12
        )


def test_split_by_fraction_and_index():
    u, y = np.arange(10.0), -np.arange(10.0)
    est, val = IOData(u, y).split(0.7)
    assert est.N == 7 and val.N == 3 and float(val.u[0, 0]) == 7.0
    est, val = IOData(u, y).split(4)
    assert est.N == 4 and float(val.y[0, 0]) == -4.0
    two = IOData.experiments([IOData(u, y), IOData(u[:6], y[:6])])
    est, val = two.split(0.5)
    assert est.lengths == [5, 3] and val.lengths == [5, 3]
    with pytest.raises(InputValidationError, match="ambiguous"):
        two.split(3)
    with pytest.raises(InputValidationError, match="empty part"):
        IOData(u, y).split(10)


def test_indexing_selects_data_sets_only():
    """``data[...]`` selects batch members; an index reaching the samples or channels (it
    cut the record to 10 samples, or read the batch axis as time) and a negative step are
    named errors, and Ts, a sample time that is not a number, too."""
    d = IOData(torch.zeros(50, 2), torch.arange(150.0).reshape(3, 50, 1))
    assert d[1].N == 50 and d[1].batch_shape == () and float(d[1].y[0, 0]) == 50.0
    assert d[..., 1:].batch_shape == (2,) and d[..., 1:].nu == 2
    assert d[torch.tensor([True, False, True])].batch_shape == (2,)
    for index in [(0, slice(None, 10)), (Ellipsis, 0, 0), (slice(None, None, -1),)]:
        with pytest.raises(InputValidationError):
            d[index]
    # a flag and a string were taken (True as 1 s, "0.1" as 0.1 s)
    for Ts in ("abc", None, np.array([0.1, 0.2]), True, "0.1", float("inf")):
        with pytest.raises(InputValidationError, match="sample time"):
            IOData(torch.zeros(5, 1), torch.zeros(5, 1), Ts=Ts)
    with pytest.raises(InputValidationError, match="skip must be an integer"):
        d.samples_after("a")


def test_time_grid_is_one_experiments():
    """``t`` of data with several experiments was one grid running on over the joined
    samples ([0, 1, 2, 3, 4] for lengths 3 and 2, where each experiment starts at 0): it is
    refused, and each experiment gives its own."""
    parts = [
        IOData(torch.zeros(3, 1), torch.zeros(3, 1)),
        IOData(torch.zeros(2, 1), torch.zeros(2, 1)),
    ]
    data = IOData.experiments(parts)
    with pytest.raises(InputValidationError, match="experiment_list"):
        _ = data.t
    assert [p.t.tolist() for p in data.experiment_list] == [[0.0, 1.0, 2.0], [0.0, 1.0]]
