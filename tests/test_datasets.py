"""The versioned data sets of datasets/ (experiments/make_datasets.py) against independent truth:
a fresh regeneration, this project's integrators on the reference ODEs, scipy's exact ZOH
response of the plant, and identification recovering the exact discretised parameters."""

import shutil

import numpy as np
import pytest
import torch
from scipy import signal

from experiments import identify_mass_spring_damper as job
from experiments import make_datasets
from experiments._datasets import DATASETS_DIR, available, load_csv, load_iodata
from integrators import InputValidationError, odeint, solve_implicit_ode
from sysid import OE, fit, fit_percent
from sysid.zoo import Lorenz, StiffVanDerPol, VanDerPol


def _states(columns: dict[str, np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
    """(t (T,), x (T, n)) float64 tensors of a reference trajectory's columns."""
    t = torch.from_numpy(columns["t"])
    x = torch.from_numpy(np.column_stack([v for k, v in columns.items() if k != "t"]))
    return t, x


def _relative_error(x: torch.Tensor, ref: torch.Tensor) -> float:
    """max |x - ref| per column over that column's largest |ref|, worst column."""
    return float(((x - ref).abs().amax(0) / ref.abs().amax(0)).max())


def test_every_generated_set_is_stored():
    assert available() == sorted(d.name for d in make_datasets.DATASETS)


def test_stored_files_equal_a_fresh_regeneration():
    rows = make_datasets.main(["--check", "--quick"])
    assert {r["file"] for r in rows} == {f"{d.name}.csv" for d in make_datasets.DATASETS if d.cheap}
    assert all(r["ok"] for r in rows)


def test_check_names_the_file_and_the_difference(tmp_path):
    shutil.copytree(DATASETS_DIR, tmp_path, dirs_exist_ok=True)
    path = tmp_path / "msd_validation.csv"
    lines = path.read_text().splitlines()
    t, u, y, y_clean = lines[500].split(",")
    lines[500] = ",".join([t, u, repr(float(y) + 1e-6), y_clean])
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(SystemExit) as failure:
        make_datasets.main(["--check", "--quick", "--out", str(tmp_path)])
    message = str(failure.value)
    assert "msd_validation.csv" in message and "'y'" in message
    scale = np.abs(load_csv("msd_validation")["y"]).max()
    assert f"{1e-6 / scale:.3g}" in message  # the largest (relative) difference
    assert "msd_identification" not in message  # the untouched files pass


@pytest.mark.parametrize("bad", ["nan", "inf"])
def test_check_fails_on_a_stored_nan_or_infinity(tmp_path, bad):
    """A stored NaN or infinity is a difference the check must report: a NaN difference
    never exceeded the worst column's score, so a corrupted file passed as ok."""
    shutil.copytree(DATASETS_DIR, tmp_path, dirs_exist_ok=True)
    path = tmp_path / "vdp_reference.csv"
    lines = path.read_text().splitlines()
    fields = lines[7].split(",")
    fields[1] = bad
    lines[7] = ",".join(fields)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(SystemExit) as failure:
        make_datasets.main(["--check", "--quick", "--out", str(tmp_path)])
    message = str(failure.value)
    assert "vdp_reference.csv" in message and "largest difference inf" in message


def test_unknown_name_lists_the_available_sets():
    with pytest.raises(InputValidationError, match="available: .*msd_identification"):
        load_csv("msd_identificaton")
    with pytest.raises(InputValidationError, match="use load_csv for trajectories"):
        load_iodata("vdp_reference")


@pytest.mark.parametrize(
    ("name", "plant"),
    [
        ("vdp_reference", VanDerPol(mu=1.0)),
        ("lorenz_reference", Lorenz(sigma=10.0, rho=28.0, beta=3.0)),
    ],
)
def test_nonstiff_references_satisfy_their_odes(name, plant):
    """Our adaptive dopri5 on the zoo models (eq. 6.43, 6.9) reproduces scipy's DOP853."""
    t, ref = _states(load_csv(name))
    with torch.no_grad():
        sol = odeint(plant, ref[0], t, method="dopri5", rtol=1e-10, atol=1e-12)
    assert _relative_error(sol.x, ref) < 1e-7


def test_stiff_vdp_reference_satisfies_its_ode():
    """Our adaptive Radau IIA (s = 3) on the zoo's stiff Van der Pol reproduces scipy Radau."""
    t, ref = _states(load_csv("stiff_vdp_reference"))
    plant = StiffVanDerPol(eps=make_datasets.STIFF_EPS)  # float64 parameter, float64 states
    with torch.no_grad():
        sol = solve_implicit_ode(plant, ref[0], t, "radau_iia", rtol=1e-10, atol=1e-10)
    assert _relative_error(sol.x, ref) < 1e-6


@pytest.mark.parametrize("name", ["msd_identification", "msd_validation"])
def test_msd_data_are_the_exact_zoh_response_plus_white_noise(name):
    """y_noise_free equals scipy's exact ZOH discretisation (eq. 1.55) driven by u up to the
    RK4 error (h = 0.05 s); y - y_noise_free has the stated standard deviation 0.02."""
    data = load_csv(name)
    m, xi, K = (job.TRUE_PHYSICAL[k] for k in ("m", "xi", "K"))
    A, B = np.array([[0.0, 1.0], [-K / m, -xi / m]]), np.array([[0.0], [1.0 / m]])
    continuous = (A, B, np.array([[1.0, 0.0]]), np.array([[0.0]]))
    Ad, Bd, C, D, Ts = signal.cont2discrete(continuous, make_datasets.TS, method="zoh")
    _, y_exact, _ = signal.dlsim((Ad, Bd, C, D, Ts), data["u"])
    y_exact = y_exact[:, 0]
    assert np.abs(data["y_noise_free"] - y_exact).max() < 1e-5 * np.abs(y_exact).max()
    assert set(np.unique(data["u"])) == {-1.0, 1.0}
    noise = data["y"] - data["y_noise_free"]
    n = len(noise)
    assert abs(noise.mean()) < 4 * make_datasets.NOISE_STD / np.sqrt(n)
    assert abs(noise.std() / make_datasets.NOISE_STD - 1) < 4 / np.sqrt(2 * n)


def test_oe_fit_on_stored_data_recovers_the_true_parameters():
    """OE(2, 2, 1) by Gauss-Newton on msd_identification: the exact ZOH parameters lie within
    4 reported standard errors, and the model fits the independent validation record."""
    data = load_iodata("msd_identification")
    assert data.Ts == make_datasets.TS and data.N == make_datasets.N_SAMPLES
    result = fit(OE(2, 2, 1, Ts=data.Ts), data, method="gauss_newton")
    assert bool(result.converged)
    truth = job.true_oe_parameters(data.Ts)
    for j, name in enumerate(result.parameter_names):
        error = abs(float(result.theta[j]) - truth[name])
        assert error < 4 * float(result.standard_errors[j]), name
    val = load_iodata("msd_validation")
    with torch.no_grad():
        fit_val = float(fit_percent(val.y, result.model.simulate(val.u)).reshape(-1)[0])
    assert fit_val > 90.0
