"""Each explicit-method experiment runs with --quick into tmp_path; its CSV is checked against
independent truth (closed forms, notes §6.1-6.5)."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from experiments._common import figure_defects


def read_csv(path) -> list[dict]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def by_key(rows: list[dict], key: str) -> dict[str, dict]:
    return {row[key]: row for row in rows}


# ------------------------------------------------------------------ _common
def test_common_helpers_write_csv_markdown_and_png(tmp_path):
    from experiments._common import experiment_parser, output_dir, plt, save_figure, write_table

    args = experiment_parser("demo", "demo").parse_args(["--quick", "--out", str(tmp_path / "d")])
    assert args.quick
    out = output_dir(args, "demo")
    assert out.is_dir()
    md = write_table([{"a": 1, "b": 0.123456789}, {"a": 2, "c": "x"}], out / "t")
    assert md.splitlines()[0] == "| a | b | c |"
    assert "0.1235" in md
    rows = read_csv(out / "t.csv")
    assert float(rows[0]["b"]) == 0.123456789 and rows[1]["c"] == "x" and rows[1]["b"] == ""
    fig, ax = plt.subplots()
    ax.plot([0, 1])
    assert save_figure(fig, out / "f.png").stat().st_size > 0


# ------------------------------------------------------------ stability regions
def test_stability_regions_intervals_match_closed_forms(tmp_path, saved_figures):
    from experiments import stability_regions

    stability_regions.main(["--quick", "--out", str(tmp_path)])
    fig = saved_figures["regions.png"]
    assert figure_defects(fig) == []
    # one curve and one legend entry per stability function: the methods with the same R(z)
    # (two-stage order 2; the two four-stage order-4 methods) share their curve
    legend = [t.get_text() for t in fig.axes[1].get_legend().get_texts()]
    assert legend == ["euler", "midpoint = heun = ralston", "kutta3", "rk4 = rk38", "dopri5"]
    assert (tmp_path / "regions.png").exists() and (tmp_path / "stability_intervals.md").exists()
    rows = by_key(read_csv(tmp_path / "stability_intervals.csv"), "method")

    def real_boundary(coeffs) -> float:
        """Left end of the stable interval [x*, 0] of the polynomial R(x) = sum_k coeffs[k] x^k:
        the negative real root of R(x) = 1 or R(x) = -1 closest to 0."""
        crossings = []
        for target in (1.0, -1.0):
            poly = np.array(coeffs[::-1], dtype=float)
            poly[-1] -= target
            crossings += [r.real for r in np.roots(poly) if abs(r.imag) < 1e-9 and r.real < -1e-9]
        return max(crossings)

    def taylor(order: int) -> list[float]:
        return [1 / math.factorial(k) for k in range(order + 1)]

    for name, order in [("euler", 1), ("midpoint", 2), ("heun", 2), ("kutta3", 3), ("rk4", 4)]:
        assert float(rows[name]["real_min"]) == pytest.approx(
            real_boundary(taylor(order)), abs=1e-9
        )
    assert float(rows["euler"]["real_min"]) == pytest.approx(-2.0, abs=1e-9)  # eq. 6.13
    assert float(rows["rk4"]["real_min"]) == pytest.approx(-2.785293563, abs=1e-8)
    # Dormand-Prince: R = Taylor_5 + z^6 / 600
    dopri = real_boundary(taylor(5) + [1 / 600])
    assert float(rows["dopri5"]["real_min"]) == pytest.approx(dopri, abs=1e-9)
    assert dopri == pytest.approx(-3.3066, abs=1e-4)
    # imaginary axis: |R(iy)|^2 = 1 - y^4/12 + y^6/36 (RK3), 1 - y^6/72 + y^8/576 (RK4)
    assert float(rows["kutta3"]["imag_max"]) == pytest.approx(math.sqrt(3), abs=1e-9)
    assert float(rows["rk4"]["imag_max"]) == pytest.approx(math.sqrt(8), abs=1e-9)
    assert float(rows["rk38"]["imag_max"]) == pytest.approx(math.sqrt(8), abs=1e-9)
    for name in ("euler", "midpoint", "heun", "ralston"):
        assert float(rows[name]["imag_max"]) == 0.0  # |R(iy)| > 1 for all y != 0
    # the regions grow with the order (Fig. 6.14)
    assert (
        float(rows["dopri5"]["real_min"])
        < float(rows["rk4"]["real_min"])
        < float(rows["kutta3"]["real_min"])
        < float(rows["heun"]["real_min"])
    )


# --------------------------------------------------------------- Euler stability
def test_euler_stability_grows_iff_dt_above_two_over_lambda(tmp_path):
    from experiments import euler_stability

    euler_stability.main(["--quick", "--out", str(tmp_path)])
    assert (tmp_path / "euler_stability.png").exists()
    rows = read_csv(tmp_path / "euler_stability.csv")
    assert {float(r["dt"]) for r in rows} >= {0.05, 0.1, 0.19, 0.2, 0.21, 0.3}
    for row in rows:
        dt, n, x_n = float(row["dt"]), int(row["n_steps"]), float(row["abs_x_N"])
        # eq. (6.12): x_N = (1 - lambda dt)^N x_0, lambda = 10
        assert x_n == pytest.approx(abs(1 - 10 * dt) ** n, rel=1e-9, abs=1e-300)
        assert (x_n > 1.0 + 1e-9) == (dt > 0.2 + 1e-12)  # eq. (6.13): unstable iff dt > 2/lambda
        assert (row["grows"] == "True") == (dt > 0.2 + 1e-12)
    by_dt = {float(r["dt"]): float(r["abs_x_N"]) for r in rows}
    assert by_dt[0.2] == pytest.approx(1.0, abs=1e-9)  # |1 - 2| = 1: marginally stable
    assert by_dt[0.3] > 1e2 and by_dt[0.05] < 1e-10


# ------------------------------------------------------------------ stiff RK4
def test_stiff_rk4_bounded_below_limit_blows_up_above(tmp_path, saved_figures):
    from experiments import stiff_rk4
    from integrators import tableau
    from sysid.zoo import StiffLinear

    stiff_rk4.main(["--quick", "--out", str(tmp_path)])
    assert saved_figures
    for name, fig in saved_figures.items():
        assert figure_defects(fig) == [], name  # labelled axes, legible ticks
    rows = by_key(read_csv(tmp_path / "stiff_rk4.csv"), "case")
    # independent limit: |R_rk4(lambda dt)| = 1 on the fast eigenvalue, by bisection
    A = StiffLinear(eps=5e-4).matrix().detach().numpy()
    lam = min(np.linalg.eigvals(A), key=lambda v: v.real)
    assert lam.real == pytest.approx(-0.1 / 5e-4, rel=1e-3) and abs(lam.imag) == pytest.approx(
        1 / 5e-4, rel=1e-3
    )
    R = tableau("rk4").stability_function
    lo, hi = 1e-4, 5e-3  # stable at lo, unstable at hi
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if abs(R(lam * mid)) <= 1 else (lo, mid)
    dt_star = float(rows["limits"]["dt"])
    assert dt_star == pytest.approx(lo, rel=1e-9)
    assert dt_star == pytest.approx(1.468e-3, rel=1e-3)
    # along the eigenvalue ray the boundary is further out than the real-axis limit 2.785
    assert float(rows["limits"]["naive_real_axis_dt"]) < dt_star
    below, above = rows["0.95 dt*"], rows["1.05 dt*"]
    assert float(below["final_error"]) < 1e-6 and float(below["max_error"]) < 1e-2
    assert float(above["final_error"]) > 1e6
    assert float(rows["notes 1.5e-3"]["dt_over_dt_star"]) > 1.0  # the figure's dt: just above
    assert float(rows["notes 1.5e-3"]["final_error"]) > 1.0


# -------------------------------------------------------------------- Lorenz
def test_lorenz_euler_departs_later_for_smaller_dt(
    tmp_path, saved_figures, reference_slope_mismatches
):
    from matplotlib.colors import to_hex

    from experiments import lorenz_euler

    lorenz_euler.main(["--quick", "--out", str(tmp_path)])
    fig = saved_figures["lorenz_euler.png"]
    assert figure_defects(fig) == []
    legend = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert legend[:3] == ["x1", "x2", "x3"] and "departure time" in legend
    for ax in fig.axes[:3]:  # the three components in three colours, each as Euler + reference
        colours = [to_hex(line.get_color()) for line in ax.lines if len(line.get_xdata()) > 2]
        assert len(set(colours)) == 3 and len(colours) == 6
    assert any(line.get_linestyle() == ":" for line in fig.axes[3].lines)  # slope-1 guide
    rows = read_csv(tmp_path / "departure.csv")
    rows.sort(key=lambda r: -float(r["dt"]))
    assert [float(r["dt"]) for r in rows] == pytest.approx([1e-2, 10**-2.5, 1e-3])
    times = [float(r["departure_time"]) for r in rows]
    assert times[0] < times[1] < times[2]
    errors_t1 = [float(r["error_at_t1"]) for r in rows]
    assert errors_t1[0] > errors_t1[1] > errors_t1[2]
    slope = float(read_csv(tmp_path / "global_error.csv")[0]["fitted_slope"])
    assert slope == pytest.approx(1.0, abs=0.1)  # eq. (6.7): Euler's global error is O(dt)


# ---------------------------------------------------------------- convergence
def test_convergence_slopes_equal_orders(tmp_path, saved_figures, reference_slope_mismatches):
    from experiments import convergence_explicit
    from integrators import tableau

    convergence_explicit.main(["--quick", "--out", str(tmp_path)])
    fig = saved_figures["convergence.png"]
    assert figure_defects(fig) == []
    for ax in fig.axes:  # every curve has its reference slope dt^p, p its order
        assert len([line for line in ax.lines if "(p = " in line.get_label()]) == 8
        assert reference_slope_mismatches(ax) == []
    rows = read_csv(tmp_path / "convergence.csv")
    methods = {r["method"] for r in rows}
    assert methods == {"euler", "midpoint", "heun", "ralston", "kutta3", "rk4", "rk38", "dopri5"}
    assert {r["problem"] for r in rows} == {"linear", "nonautonomous", "quadratic"}
    for row in rows:
        order, slope = int(row["order"]), float(row["fitted_slope"])
        assert order == tableau(row["method"]).order
        if (row["problem"], row["method"]) == ("quadratic", "dopri5"):
            # documented pre-asymptotic case: the local slope falls from ~7 towards 5 but is
            # still ~5.3-5.6 where round-off sets in
            assert 4.85 < slope < 5.8, row
        else:
            assert slope == pytest.approx(order, abs=0.15), row


# ------------------------------------------------------------ dopri5 step sizes
def test_dopri5_steps_shrink_where_the_solution_moves_fast(tmp_path, saved_figures):
    from experiments import dopri5_steps

    dopri5_steps.main(["--quick", "--out", str(tmp_path)])
    assert saved_figures
    for name, fig in saved_figures.items():
        assert figure_defects(fig) == [], name  # labelled axes, legible ticks
    rows = {float(r["mu"]): r for r in read_csv(tmp_path / "dopri5_steps.csv")}
    relax = rows[5.0]  # relaxation oscillation: slow drift, then fast jumps (Fig. 6.17)
    assert float(relax["mean_dt_fast_quartile"]) < 0.5 * float(relax["mean_dt_slow_quartile"])
    assert float(relax["corr_log_dt_log_speed"]) < -0.4
    speed_small = float(relax["median_speed_at_smallest_10pct_dt"])
    assert speed_small > 3.0 * float(relax["median_speed"])
    assert float(relax["speed_rank_at_dt_min"]) > 0.5
    assert float(relax["dt_max"]) > 5.0 * float(relax["dt_min"])
    # eq. (6.43) as printed (mu = 1): the same tendency, much weaker
    plain = rows[1.0]
    assert float(plain["mean_dt_fast_quartile"]) < float(plain["mean_dt_slow_quartile"])


def test_accepted_steps_reconstruction_matches_solver_counters():
    """The steps recovered from the rhs call times tile [0, T] and agree with a rerun that
    stops after k attempts (``stats.extra['t_reached']``)."""
    import torch

    from experiments.dopri5_steps import accepted_steps
    from integrators import odeint
    from sysid.zoo import VanDerPol

    plant, x0 = VanDerPol(mu=1.0), torch.tensor([0.0, 2.0], dtype=torch.float64)
    t_k, h_k, n_rej, sol = accepted_steps(plant, x0, 3.0, 1e-6, 1e-6)
    assert t_k[0] == 0.0 and np.allclose(t_k[1:], t_k[:-1] + h_k[:-1], rtol=0, atol=1e-14)
    assert t_k[-1] + h_k[-1] == pytest.approx(3.0, rel=1e-14)
    attempts = len(h_k) + n_rej
    with torch.no_grad():
        partial = odeint(
            plant,
            x0,
            torch.tensor([0.0, 3.0], dtype=torch.float64),
            method="dopri5",
            rtol=1e-6,
            atol=1e-6,
            max_steps=attempts // 2,
        )
    reached = float(partial.stats.extra["t_reached"])
    n_acc = int(partial.stats.n_steps)
    assert reached == pytest.approx(t_k[n_acc], rel=1e-14)


# ------------------------------------------------------------- work-precision
def test_work_precision_slopes_and_costs(tmp_path):
    from experiments import work_precision_explicit
    from integrators import tableau

    work_precision_explicit.main(["--quick", "--out", str(tmp_path)])
    summary = [r for r in read_csv(tmp_path / "summary.csv") if r["problem"] == "linear"]
    rows = by_key(summary, "method")
    for name in ("euler", "midpoint", "heun", "ralston", "kutta3", "rk4", "rk38", "dopri5"):
        slope = float(rows[name]["slope_error_vs_evals"])
        assert slope == pytest.approx(-tableau(name).order, abs=0.2), name
    # eq. (6.37): n = N s for fixed steps (dopri5 at fixed step skips its FSAL stage: s - 1)
    for point in read_csv(tmp_path / "points.csv"):
        if point["setting_kind"] != "n_steps":
            continue
        stages = {"dopri5": 6}.get(point["method"], tableau(point["method"]).stages)
        assert int(point["n_f_evals"]) == int(point["setting"]) * stages
    # at 1e-6 on the linear problem, higher order is cheaper (Fig. 6.13)
    cost = {name: float(rows[name]["evals_for_1e-06"]) for name in ("kutta3", "rk4", "dopri5")}
    assert cost["dopri5"] < cost["rk4"] < cost["kutta3"]
    assert float(rows["dopri5 adaptive"]["evals_for_1e-06"]) < cost["rk4"]
