"""Regenerate, or check, the small versioned data sets of ``datasets/``.

Every file is a deterministic function of the constants in this module (fixed seeds, fixed
solver tolerances), so the stored files can be rebuilt and compared at any time:

    python -m experiments.make_datasets            # write all files and datasets/README.md
    python -m experiments.make_datasets --check    # compare the stored files with a fresh run
    python -m experiments.make_datasets --only lorenz_reference --out /tmp/ds

Data sets (column meanings, units and parameters are in ``datasets/README.md``, which this
script writes):

* ``msd_identification``, ``msd_validation``: two independent identification experiments of
  the main job's plant (``experiments/identify_mass_spring_damper.py``): the zoo
  spring-mass-damper m y'' + xi y' + K y = u (notes eq. 1.26-1.28) driven by a random binary
  force held between samples (eq. 8.34), simulated by the main job's ``simulate_plant``,
  with white Gaussian output noise; one seeded ``torch.Generator`` per experiment.
* ``vdp_reference``, ``lorenz_reference``, ``stiff_vdp_reference``: reference trajectories of
  Van der Pol (eq. 6.43), Lorenz (eq. 6.9) and the stiff Van der Pol oscillator by scipy's
  ``solve_ivp`` at tight tolerances, independent of this project's integrators (right-hand
  sides written here in numpy, not taken from ``sysid.zoo``).

``--check`` compares column by column: ``t`` and ``u`` must be bit-for-bit equal; every other
column may differ by at most ``CHECK_RTOL`` = 1e-10 times its largest magnitude, which absorbs
round-off of another CPU or library build (vectorised ``log``/``sin`` in torch's Gaussian
sampler, a different BLAS) but not a changed seed, parameter or tolerance. ``--quick`` writes
to ``experiments/out/make_datasets/quick`` (never to ``datasets/``) and leaves out the stiff
Van der Pol reference (scipy Radau at 1e-12: about 4 s on one core; the other four sets take
about 3 s together, nearly all of it the two eager RK4 simulations).
"""

from __future__ import annotations

import argparse
import pathlib
from collections.abc import Callable
from dataclasses import dataclass

from experiments._common import (
    DATASETS_DIR,
    experiment_parser,
    finish,
    markdown_table,
    output_dir,
    parse_early,
    progress,
)

NAME = "make_datasets"
#: The names of ``DATASETS`` below, in their order (``--only`` choices, known before the imports).
DATASET_NAMES = (
    "msd_identification",
    "msd_validation",
    "vdp_reference",
    "lorenz_reference",
    "stiff_vdp_reference",
)


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(
        NAME, "Regenerate or check the versioned data sets of datasets/.", DATASETS_DIR
    )
    parser.add_argument(
        "--check",
        action="store_true",
        help="regenerate in memory and compare with the files in --out (exit 1 on mismatch)",
    )
    parser.add_argument(
        "--only",
        nargs="+",
        choices=DATASET_NAMES,
        metavar="NAME",
        help=f"data sets to write or check, of: {', '.join(DATASET_NAMES)} (default: all)",
    )
    return parser


parse_early(__name__, build_parser)

import numpy as np
import torch
from scipy.integrate import solve_ivp

from experiments import identify_mass_spring_damper as job
from experiments._datasets import load_csv
from integrators.errors import InputValidationError
from sysid.montecarlo import input_signal, noise_signal

#: Identification experiments (as in the main job's ``main``).
TS = 0.1  # sample time [s]
N_SAMPLES = 1000
NOISE_STD = 0.02  # output noise standard deviation [m]
HOLD = 3  # samples each binary input level is held
SUBSTEPS = 2  # RK4 steps per sample (h = 0.05 s)
IDENTIFICATION_SEED = 0
VALIDATION_SEED = 1

#: Reference trajectories.
VDP_X0 = (0.0, 2.0)  # as in experiments/dopri5_steps.py and stiff_work_precision.py
LORENZ_X0 = (1.0, 1.0, 1.0)  # as in experiments/lorenz_euler.py
LORENZ_SIGMA, LORENZ_RHO, LORENZ_BETA = 10.0, 28.0, 3.0  # the notes' beta, not the classic 8/3
STIFF_EPS = 1e-6
STIFF_Y0 = (2.0, 0.0)
NONSTIFF_TOL = 1e-13  # DOP853 rtol = atol
STIFF_TOL = 1e-12  # Radau rtol = atol

#: --check: largest allowed difference of a non-exact column, relative to its largest |value|.
CHECK_RTOL = 1e-10
EXACT_COLUMNS = ("t", "u")

COMMAND = "python -m experiments.make_datasets"


@dataclass(frozen=True)
class DataSet:
    """One file of ``datasets/``: how it is generated and how README.md describes it.

    Attributes:
        name: file stem (``<name>.csv``).
        title: one line for the README.
        description: a Markdown paragraph.
        columns: column name -> meaning and unit, in file order.
        parameters: generating parameters, name -> value as shown in the README.
        generate: ``() -> {column: (n_rows,) float64 array}``, deterministic.
        cheap: False for the sets that ``--quick`` leaves out.
        remarks: Markdown paragraphs appended to the file's README section.
    """

    name: str
    title: str
    description: str
    columns: dict[str, str]
    parameters: dict[str, str]
    generate: Callable[[], dict[str, np.ndarray]]
    cheap: bool = True
    remarks: tuple[str, ...] = ()


# ----------------------------------------------------------------------------- generators
def msd_experiment(seed: int) -> dict[str, np.ndarray]:
    """One identification experiment of the main job's plant, columns of shape (N_SAMPLES,).

    Draws from ``torch.Generator().manual_seed(seed)`` in a fixed order: the binary input
    (``input_signal("prbs", hold=HOLD)``, +-1 N), then the output noise (Gaussian, std
    ``NOISE_STD`` m). ``y_noise_free`` is the main job's ``simulate_plant`` (RK4, ``SUBSTEPS``
    steps per sample, from rest, zero-order-hold input, eq. 8.34) at t_k = k TS.
    """
    gen = torch.Generator().manual_seed(seed)
    u = input_signal("prbs", N_SAMPLES, hold=HOLD, generator=gen)  # (N, 1)
    p = torch.tensor([job.TRUE_PHYSICAL[k] for k in job.PHYSICAL_NAMES], dtype=torch.float64)
    with torch.no_grad():
        y_clean = job.simulate_plant(p, u, TS, SUBSTEPS)  # (N, 1)
    y = y_clean + noise_signal(y_clean.shape, "gaussian", std=NOISE_STD, generator=gen)
    t = TS * torch.arange(N_SAMPLES, dtype=torch.float64)  # the grid of simulate_plant
    return {
        "t": t.numpy(),
        "u": u[:, 0].numpy(),
        "y": y[:, 0].numpy(),
        "y_noise_free": y_clean[:, 0].numpy(),
    }


def vdp_rhs(t, x):
    """Van der Pol, eq. (6.43): x1' = (1 - x2^2) x1 - x2, x2' = x1 (mu = 1)."""
    return [(1.0 - x[1] ** 2) * x[0] - x[1], x[0]]


def lorenz_rhs(t, x):
    """Lorenz, eq. (6.9), with LORENZ_SIGMA, LORENZ_RHO, LORENZ_BETA."""
    return [
        LORENZ_SIGMA * (x[1] - x[0]),
        x[0] * (LORENZ_RHO - x[2]) - x[1],
        x[0] * x[1] - LORENZ_BETA * x[2],
    ]


def stiff_vdp_rhs(t, y):
    """Stiff Van der Pol: y1' = y2, y2' = ((1 - y1^2) y2 - y1) / STIFF_EPS."""
    return [y[1], ((1.0 - y[0] ** 2) * y[1] - y[0]) / STIFF_EPS]


def reference_trajectory(rhs, x0, t: np.ndarray, method: str, tol: float) -> np.ndarray:
    """x(t_i) of x' = rhs(t, x), x(t_0) = x0, by ``solve_ivp(method, rtol=atol=tol)``.

    Integrated interval by interval, each restarted from the previous end point, so every
    output time is a step end point: no dense-output interpolation error enters.

    Returns:
        ``(len(t), len(x0))`` float64 array.
    """
    states = [np.asarray(x0, dtype=np.float64)]
    for t_start, t_end in zip(t[:-1], t[1:], strict=True):
        result = solve_ivp(rhs, (t_start, t_end), states[-1], method=method, rtol=tol, atol=tol)
        if not result.success:
            raise RuntimeError(f"{method} failed on [{t_start}, {t_end}]: {result.message}")
        states.append(result.y[:, -1])
    return np.stack(states)


def _trajectory(rhs, x0, t, method, tol, names) -> dict[str, np.ndarray]:
    x = reference_trajectory(rhs, x0, t, method, tol)
    return {"t": t, **{name: x[:, j] for j, name in enumerate(names)}}


# ----------------------------------------------------------------------------- catalogue
def _msd_parameters(seed: int) -> dict[str, str]:
    truth = job.true_oe_parameters(TS)
    return {
        "plant": "m y'' + xi y' + K y = u (notes eq. 1.26-1.28), sysid.zoo.SpringMassDamper",
        "m, xi, K": ", ".join(f"{job.TRUE_PHYSICAL[k]:g}" for k in job.PHYSICAL_NAMES)
        + " (kg, N s/m, N/m)",
        "input": f"random binary +-1 N, each level held {HOLD} samples "
        f'(sysid.montecarlo.input_signal("prbs", hold={HOLD})), zero-order hold between '
        "samples (eq. 8.34)",
        "simulation": f"main job's simulate_plant: fixed-step RK4, {SUBSTEPS} steps per sample "
        f"(h = {TS / SUBSTEPS:g} s), from rest x(0) = 0",
        "Ts, N": f"{TS:g} s, {N_SAMPLES}",
        "output noise": f"white Gaussian, std {NOISE_STD:g} m (sysid.montecarlo.noise_signal)",
        "seed": f"torch.Generator().manual_seed({seed}); input drawn first, then the noise",
        "true OE(nb=2, nf=2, nk=1)": "exact ZOH discretisation (eq. 1.55): "
        + ", ".join(f"{k} = {v:.10g}" for k, v in truth.items()),
    }


_MSD_COLUMNS = {
    "t": "sample time t_k = k Ts [s]",
    "u": "input force, held constant on [t_k, t_k+1) [N]",
    "y": "measured position y_noise_free + noise [m]",
    "y_noise_free": "simulated position at t_k [m]",
}
_MSD_REMARK = (
    "`y_noise_free` is the RK4 simulation; it differs from the exact ZOH response by about "
    "5e-6 of its largest magnitude, far below the noise. The true discrete-time model is the "
    "exact ZOH discretisation listed above."
)


def _reference_parameters(ode: str, x0, t, method: str, tol: float) -> dict[str, str]:
    return {
        "ODE": ode,
        "x(0)": "(" + ", ".join(f"{v:g}" for v in x0) + ")",
        "output times": f"numpy.linspace({t[0]:g}, {t[-1]:g}, {len(t)})",
        "solver": f'scipy.integrate.solve_ivp(method="{method}", rtol={tol:g}, atol={tol:g}), '
        "restarted at every output time (no dense-output interpolation)",
    }


VDP_T = np.linspace(0.0, 10.0, 101)
LORENZ_T = np.linspace(0.0, 2.0, 201)
STIFF_T = np.linspace(0.0, 2.0, 41)

DATASETS = (
    DataSet(
        "msd_identification",
        "identification experiment of the main job's spring-mass-damper",
        "One noisy input/output record for identifying the plant of "
        "`experiments/identify_mass_spring_damper.py`; load it with "
        '`experiments._datasets.load_iodata("msd_identification")`.',
        _MSD_COLUMNS,
        _msd_parameters(IDENTIFICATION_SEED),
        lambda: msd_experiment(IDENTIFICATION_SEED),
        remarks=(_MSD_REMARK,),
    ),
    DataSet(
        "msd_validation",
        "independent validation experiment of the same plant",
        "Same plant, input class and noise level as `msd_identification`, another seed: "
        "fresh data for validating a model identified on `msd_identification`.",
        _MSD_COLUMNS,
        _msd_parameters(VALIDATION_SEED),
        lambda: msd_experiment(VALIDATION_SEED),
        remarks=(_MSD_REMARK,),
    ),
    DataSet(
        "vdp_reference",
        "Van der Pol oscillator (mu = 1), reference trajectory",
        "High-accuracy solution of Van der Pol, notes eq. (6.43), the ODE of Fig. 6.17.",
        {"t": "time", "x1": "state x1", "x2": "state x2"},
        _reference_parameters(
            "x1' = (1 - x2^2) x1 - x2, x2' = x1 (eq. 6.43)", VDP_X0, VDP_T, "DOP853", NONSTIFF_TOL
        ),
        lambda: _trajectory(vdp_rhs, VDP_X0, VDP_T, "DOP853", NONSTIFF_TOL, ("x1", "x2")),
    ),
    DataSet(
        "lorenz_reference",
        "Lorenz system, reference trajectory",
        "High-accuracy solution of the Lorenz system, notes eq. (6.9), with the notes' "
        "parameters (beta = 3, not the classic 8/3, as in Fig. 6.2-6.5 and "
        "`experiments/lorenz_euler.py`) and initial state.",
        {"t": "time", "x1": "state x1", "x2": "state x2", "x3": "state x3"},
        _reference_parameters(
            f"x1' = sigma (x2 - x1), x2' = x1 (rho - x3) - x2, x3' = x1 x2 - beta x3 (eq. 6.9); "
            f"sigma = {LORENZ_SIGMA:g}, rho = {LORENZ_RHO:g}, beta = {LORENZ_BETA:g}",
            LORENZ_X0,
            LORENZ_T,
            "DOP853",
            NONSTIFF_TOL,
        ),
        lambda: _trajectory(
            lorenz_rhs, LORENZ_X0, LORENZ_T, "DOP853", NONSTIFF_TOL, ("x1", "x2", "x3")
        ),
    ),
    DataSet(
        "stiff_vdp_reference",
        "stiff Van der Pol oscillator (eps = 1e-6), reference trajectory",
        "High-accuracy solution of the singularly perturbed Van der Pol oscillator "
        "(`sysid.zoo.StiffVanDerPol`, the stiff problem of Fig. 7.3): a boundary layer of "
        "width ~eps at t = 0, slow motion on the manifold y2 = y1 / (1 - y1^2), a fast jump "
        "near t = 0.81.",
        {"t": "time", "y1": "state y1", "y2": "state y2"},
        _reference_parameters(
            f"y1' = y2, y2' = ((1 - y1^2) y2 - y1) / eps, eps = {STIFF_EPS:g}",
            STIFF_Y0,
            STIFF_T,
            "Radau",
            STIFF_TOL,
        ),
        lambda: _trajectory(stiff_vdp_rhs, STIFF_Y0, STIFF_T, "Radau", STIFF_TOL, ("y1", "y2")),
        cheap=False,
    ),
)
BY_NAME = {d.name: d for d in DATASETS}


# ----------------------------------------------------------------------------- files
def csv_text(columns: dict[str, np.ndarray]) -> str:
    """A header row and one row per sample; numbers as Python's shortest round-trip repr."""
    rows = np.column_stack([np.asarray(v, dtype=np.float64) for v in columns.values()])
    lines = [",".join(columns)] + [",".join(map(repr, row)) for row in rows.tolist()]
    return "\n".join(lines) + "\n"


def readme_text() -> str:
    """``datasets/README.md``: what each file is, its columns, parameters and command."""
    lines = [
        "# Data sets",
        "",
        "Small, versioned data sets for experiments and tests. Every file is regenerated "
        "deterministically (fixed seeds, fixed solver tolerances) by "
        "`experiments/make_datasets.py`, which also writes this README: edit the script, "
        "not this file. Library code (`integrators/`, `sysid/`) never reads this folder.",
        "",
        f"- regenerate all files: `{COMMAND}`",
        f"- compare the stored files with a fresh regeneration: `{COMMAND} --check` "
        "(exit status 1 and a message naming the file, column and largest difference when "
        "they disagree; `--quick` leaves out the stiff Van der Pol reference, the one set "
        "that takes seconds)",
        "- read them: `experiments._datasets.load_csv(name)` (columns as float64 numpy "
        "arrays) or `load_iodata(name)` (identification data as `sysid.IOData`)",
        "",
        "Format: CSV, one header row of column names, one row per sample, every number "
        "written as Python's shortest `repr` that reads back as the same float64. Time "
        "columns of the reference trajectories are dimensionless (the notes give no units).",
        "",
        f"Check tolerance: the columns {', '.join(f'`{c}`' for c in EXACT_COLUMNS)} must be "
        f"bit-for-bit equal; every other column may differ by at most {CHECK_RTOL:g} times "
        "its largest magnitude. That covers round-off of another CPU or library build "
        "(torch's vectorised Gaussian sampler, BLAS, scipy), not a changed seed, parameter or "
        "tolerance.",
    ]
    for d in DATASETS:
        lines += ["", f"## `{d.name}.csv`: {d.title}", "", d.description, ""]
        lines += ["| column | meaning and unit |", "|---|---|"]
        lines += [f"| `{c}` | {meaning} |" for c, meaning in d.columns.items()]
        lines += [""] + [f"- {key}: {value}" for key, value in d.parameters.items()]
        lines += [f"- regenerate: `{COMMAND} --only {d.name}`"]
        lines += [f"\n{remark}" for remark in d.remarks]
    return "\n".join(lines) + "\n"


def compare(name: str, fresh: dict[str, np.ndarray], stored: dict[str, np.ndarray]) -> dict:
    """Largest difference of a fresh regeneration from the stored file, column by column.

    Returns:
        ``{"file", "column", "max_difference", "tolerance", "ok"}`` for the column that
        exceeds its tolerance by the largest factor (or the one closest to it when all
        pass), plus ``"detail"`` when the header or the number of rows differ. Differences
        of non-exact columns are relative to the stored column's largest finite magnitude;
        ``EXACT_COLUMNS`` must agree bit for bit (tolerance 0). A NaN or infinity in one of
        the two files where the other has a different value is an infinite difference.
    """
    row = {"file": f"{name}.csv", "max_difference": np.inf, "tolerance": 0.0, "ok": False}
    if list(fresh) != list(stored):
        detail = f"stored columns {list(stored)}, generated {list(fresh)}"
        return {**row, "column": "header", "detail": detail}
    worst = None
    for column, new in fresh.items():
        old = stored[column]
        if new.shape != old.shape:
            detail = f"{len(old)} stored rows, {len(new)} generated"
            return {**row, "column": column, "detail": detail}
        exact = column in EXACT_COLUMNS
        finite = np.abs(old[np.isfinite(old)])
        largest = float(finite.max()) if finite.size else 0.0
        scale = 1.0 if exact else max(largest, np.finfo(np.float64).tiny)
        if np.array_equal(new, old, equal_nan=True):
            difference = 0.0
        else:  # a NaN or infinity in only one of them is an infinite difference
            difference = (
                float(np.nan_to_num(np.abs(new - old), nan=np.inf, posinf=np.inf).max()) / scale
            )
        tolerance = 0.0 if exact else CHECK_RTOL
        score = difference / tolerance if tolerance else (np.inf if difference else 0.0)
        if worst is None or score > worst[0]:
            worst = (score, column, difference, tolerance)
    score, column, difference, tolerance = worst
    return {
        **row,
        "column": column,
        "max_difference": difference,
        "tolerance": tolerance,
        "ok": bool(score <= 1.0),
    }


def _failure_message(row: dict, folder: pathlib.Path) -> str:
    kind = "absolute" if row["tolerance"] == 0.0 else "relative to the column's largest |value|"
    detail = row.get("detail", f"largest difference {row['max_difference']:.3g} ({kind})")
    return (
        f"{folder / row['file']}: column {row['column']!r} disagrees with a fresh "
        f"regeneration: {detail}, tolerance {row['tolerance']:g}. If the change is intended, "
        f"regenerate with `{COMMAND}`."
    )


def main(argv=None) -> list[dict]:
    parser = build_parser()
    args = parser.parse_args(argv)
    selected = [BY_NAME[n] for n in args.only] if args.only else list(DATASETS)
    if args.quick:
        selected = [d for d in selected if d.cheap]
    if not selected:
        parser.error("--quick leaves out every selected data set; drop --quick or --only.")
    if args.check:
        folder = pathlib.Path(args.out) if args.out else DATASETS_DIR
    else:
        folder = output_dir(args, NAME, DATASETS_DIR)

    rows, failures = [], []
    if args.check:
        readme = folder / "README.md"
        if not readme.is_file():
            failures.append(f"{readme} is missing; run `{COMMAND}`.")
        elif readme.read_text() != readme_text():
            failures.append(f"{readme}: differs from the generated README; run `{COMMAND}`.")
        for d in selected:
            try:
                row = compare(d.name, d.generate(), load_csv(d.name, folder))
            except InputValidationError as err:
                failures.append(str(err))
                continue
            rows.append(row)
            if not row["ok"]:
                failures.append(_failure_message(row, folder))
        if rows:
            print(markdown_table(rows))
        if failures:
            raise SystemExit("\n".join(failures))
        finish(folder)
        return rows

    (folder / "README.md").write_text(readme_text())
    for d in progress(selected, "data sets"):
        text = csv_text(d.generate())
        path = folder / f"{d.name}.csv"
        path.write_text(text)
        rows.append({"file": path.name, "rows": text.count("\n") - 1, "bytes": len(text)})
    finish(folder, markdown_table(rows))
    return rows


if __name__ == "__main__":
    main()
