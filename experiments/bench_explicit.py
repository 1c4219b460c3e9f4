"""Benchmark: fixed-step RK4 and adaptive dopri5 against torchdiffeq and torchode.

Two tables, one process, one thread, float64, errors against a tight scipy DOP853 reference:

1. Fixed-step RK4 on Van der Pol (mu = 1, notes eq. 6.43), 1000 steps of h = 0.01, batch 1,
   1024 and 65 536: this project (classic RK4 and the 3/8 rule, compiled and eager) against
   torchdiffeq's ``"rk4"`` (which is the 3/8 rule, ``rk4_alt_step_func``) and against
   torchdiffeq's own classic-RK4 step function plugged into its fixed-grid solver. The
   speed-up is torchdiffeq's wall time over ours on the same grid; the one-off compile time
   is reported separately.
2. dopri5 on 256 Van der Pol oscillators with mu spread over [0.1, 20] (t_end 10 and 20):
   this project's per-sample step control (``odeint(method="dopri5")``, PI controller),
   torchdiffeq's dopri5 (one step size for the batch) and torchode's Dopri5 (per-sample
   steps, integral controller), each run over a tolerance sweep (rtol 1e-5 ... 1e-7 in half
   decades, atol = 1e-3 rtol for all three). Three tables and a figure:

   * equal tolerance (``adaptive_dopri5``): the runs at rtol 1e-6, atol 1e-9 (the issue's
     setting), with f-evaluations, batched f calls, wall time and the error each reached;
   * matched error (``adaptive_dopri5_matched``): the target is the error ours reaches at
     rtol 1e-6; each solver's rtol, f-evaluations, batched calls and wall time at the target
     are interpolated log-log between the loosest pair of its runs that brackets it (refined
     by extra runs where a check run at the interpolated rtol misses the target by more than
     25 %), with ratios to torchdiffeq and torchode;
   * the whole sweep (``adaptive_dopri5_sweep``) and the work-precision figure
     (``adaptive_dopri5_work_precision.png``).

Run: ``python -m experiments.bench_explicit`` (full sizes, minutes) or ``--quick``.
"""

from __future__ import annotations

import argparse
import datetime
import math
import platform
import time

from experiments._common import (
    experiment_parser,
    finish,
    output_dir,
    parse_early,
    progress,
    save_figure,
    write_table,
)


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(
        "bench_explicit",
        "Fixed-step RK4 and adaptive dopri5 against torchdiffeq and torchode (Van der Pol).",
    )
    parser.add_argument("--no-compile", action="store_true", help="skip torch.compile runs")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random initial states")
    return parser


parse_early(__name__, build_parser)

import numpy as np
import scipy.integrate
import torch

from experiments._common import plt, readable_log_ticks
from integrators import odeint

try:  # the zoo's plant; a local copy keeps the benchmark usable without sysid
    from sysid.zoo import VanDerPol
except ImportError:  # pragma: no cover
    VanDerPol = None


class _LocalVanDerPol(torch.nn.Module):
    """x1' = mu (1 - x2^2) x1 - x2, x2' = x1 (notes eq. 6.43 for mu = 1)."""

    def __init__(self, mu):
        super().__init__()
        self.mu = torch.nn.Parameter(torch.as_tensor(mu, dtype=torch.float64))

    def forward(self, t, x, u=None):
        x1, x2 = x[..., 0:1], x[..., 1:2]
        return torch.cat([self.mu * (1 - x2**2) * x1 - x2, x1], dim=-1)


def van_der_pol(mu):
    return VanDerPol(mu) if VanDerPol is not None else _LocalVanDerPol(mu)


def vdp_numpy(mu):
    """Vectorised numpy right-hand side of a flattened batch (for the scipy reference)."""
    mu = np.asarray(mu, dtype=np.float64).reshape(-1)

    def f(t, y):
        x1, x2 = y[0::2], y[1::2]
        out = np.empty_like(y)
        out[0::2] = mu * (1 - x2**2) * x1 - x2
        out[1::2] = x1
        return out

    return f


def reference(mu, x0, t):
    """(B, T, 2) DOP853 solution with rtol = atol = 1e-12 (one flattened system)."""
    x0 = np.asarray(x0, dtype=np.float64)
    sol = scipy.integrate.solve_ivp(
        vdp_numpy(mu),
        (t[0], t[-1]),
        x0.reshape(-1),
        method="DOP853",
        t_eval=t,
        rtol=1e-12,
        atol=1e-12,
    )
    return sol.y.T.reshape(len(t), -1, 2).transpose(1, 0, 2)


def best_time(fn, repeats):
    """(best wall time over ``repeats`` calls, result of the last call)."""
    best, result = float("inf"), None
    for _ in range(repeats):
        tic = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - tic)
    return best, result


def _torchdiffeq_classic_rk4():
    """torchdiffeq's fixed-grid solver with its classic RK4 step (``rk4_step_func``)."""
    from torchdiffeq._impl.fixed_grid import RK4
    from torchdiffeq._impl.odeint import SOLVERS
    from torchdiffeq._impl.rk_common import rk4_step_func

    class ClassicRK4(RK4):
        def _step_func(self, func, t0, dt, t1, y0):
            f0 = func(t0, y0)
            return rk4_step_func(func, t0, dt, t1, y0, f0=f0), f0

    SOLVERS.setdefault("classic_rk4", ClassicRK4)
    return "classic_rk4"


def fixed_step_table(batches, n_steps, repeats, use_compile, seed):
    """Rows of the fixed-step RK4 comparison."""
    import torchdiffeq

    classic = _torchdiffeq_classic_rk4()
    rows = []
    f = van_der_pol(1.0)
    t = torch.linspace(0.0, 0.01 * n_steps, n_steps + 1, dtype=torch.float64)
    gen = torch.Generator().manual_seed(seed)
    for batch in progress(batches, "fixed-step RK4 batch sizes"):
        x0 = 4 * torch.rand(batch, 2, dtype=torch.float64, generator=gen) - 2
        n_ref = min(batch, 64)
        ref = reference(np.ones(n_ref), x0[:n_ref].numpy(), t.numpy())

        def error(x, ref=ref, n_ref=n_ref):
            return float(np.abs(x[:n_ref].numpy() - ref).max())

        def ours(method, compile_flag, x0=x0):
            return odeint(f, x0, t, method=method, compile=compile_flag)

        def tdq(method, x0=x0):
            return torchdiffeq.odeint(f, x0, t, method=method).transpose(0, 1)

        with torch.no_grad():
            results = {}
            for label, method in (
                ("torchdiffeq rk4 (3/8 rule)", "rk4"),
                ("torchdiffeq classic rk4", classic),
            ):
                wall, x = best_time(lambda m=method: tdq(m), repeats)
                results[label] = (wall, error(x), None, x[..., -1, :].clone())
                del x  # full outputs are large at batch 65 536: keep only the final states
            variants = [("ours rk4 eager", "rk4", False), ("ours rk38 eager", "rk38", False)]
            if use_compile:
                variants = [
                    ("ours rk4 compiled", "rk4", True),
                    ("ours rk38 compiled", "rk38", True),
                ] + variants
            for label, method, flag in variants:
                first = None
                if flag:  # the first call compiles (or loads the compiled chunk)
                    tic = time.perf_counter()
                    sol = ours(method, flag)
                    first = (time.perf_counter() - tic, sol.stats.extra["compile_s"])
                    del sol
                wall, sol = best_time(lambda m=method, c=flag: ours(m, c), repeats)
                results[label] = (wall, error(sol.x), first, sol.x[..., -1, :].clone())
                del sol
        same_method_gap = float(
            (results["ours rk38 eager"][3] - results["torchdiffeq rk4 (3/8 rule)"][3]).abs().max()
        )
        base = results["torchdiffeq rk4 (3/8 rule)"][0]
        base_classic = results["torchdiffeq classic rk4"][0]
        for label, (wall, err, first, _) in results.items():
            is_38 = "3/8" in label or "rk38" in label
            row = {
                "batch": batch,
                "steps": n_steps,
                "solver": label,
                "wall_s": wall,
                "steps_per_s": n_steps / wall,
                "speedup_vs_tdq_same_tableau": (base if is_38 else base_classic) / wall,
                "max_error": err,
                "first_call_s": None if first is None else first[0],
                "compile_s": None if first is None else first[1],
                "final_gap_to_tdq_38": same_method_gap if label == "ours rk38 eager" else None,
            }
            rows.append(row)
    return rows


ADAPTIVE_SOLVERS = {
    "ours": "ours dopri5 (per-sample steps)",
    "torchdiffeq": "torchdiffeq dopri5 (one step for the batch)",
    "torchode": "torchode Dopri5 (per-sample steps)",
}


def _adaptive_problem(batch, t_end, n_out, mu_max, seed):
    """Van der Pol batch with mu spread over [0.1, mu_max], random x0 in [-2, 2]^2, reference."""
    mu = torch.linspace(0.1, mu_max, batch, dtype=torch.float64)[:, None]
    gen = torch.Generator().manual_seed(seed)
    x0 = 4 * torch.rand(batch, 2, dtype=torch.float64, generator=gen) - 2
    t = torch.linspace(0.0, t_end, n_out, dtype=torch.float64)
    ref = reference(mu.numpy(), x0.numpy(), t.numpy())
    return {"f": van_der_pol(mu), "x0": x0, "t": t, "ref": ref, "t_end": t_end}


def run_dopri5(name, problem, rtol, atol, repeats=1):
    """One dopri5 run of solver ``name`` (a key of ``ADAPTIVE_SOLVERS``) on ``problem``.

    Measured: the wall time (best of ``repeats`` calls, under ``torch.no_grad()``), the
    number of batched right-hand-side calls (counted by a wrapper around the model), the
    f-evaluations summed over the samples and the largest per-sample count, the max abs error
    at the output times against the DOP853 reference, and whether every sample succeeded.

    The summed f-evaluations are each solver's own per-sample counters, which do not count
    the same thing: ours counts an evaluation only for samples still integrating; torchode's
    ``n_f_evals`` goes up for every sample on every batched call (so it is batched calls
    times batch size); torchdiffeq has no per-sample counter and its whole batch takes every
    step, so it is batched calls times batch size as well. Every batched call evaluates the
    model on all rows of the batch for all three, so ``batched_f_calls`` is the model work
    on one definition.
    """
    import torchdiffeq
    import torchode

    f, x0, t, ref = problem["f"], problem["x0"], problem["t"], problem["ref"]
    batch = x0.shape[0]
    calls = {"n": 0}

    def counted(t_, x):
        calls["n"] += 1
        return f(t_, x)

    with torch.no_grad():
        if name == "ours":
            wall, sol = best_time(
                lambda: odeint(counted, x0, t, method="dopri5", rtol=rtol, atol=atol), repeats
            )
            per_sample = torch.as_tensor(sol.stats.n_f_evals)
            x, total, largest = sol.x, int(per_sample.sum()), int(per_sample.max())
            success = bool(sol.success)
        elif name == "torchdiffeq":
            wall, x = best_time(
                lambda: torchdiffeq.odeint(counted, x0, t, method="dopri5", rtol=rtol, atol=atol),
                repeats,
            )
            x = x.transpose(0, 1)
            n = calls["n"] // repeats
            total, largest, success = n * batch, n, bool(torch.isfinite(x).all())
        elif name == "torchode":
            term = torchode.ODETerm(counted)
            step = torchode.Dopri5(term=term)
            control = torchode.IntegralController(atol=atol, rtol=rtol, term=term)
            solver = torchode.AutoDiffAdjoint(step, control)
            ivp = torchode.InitialValueProblem(y0=x0, t_eval=t.expand(batch, -1))
            wall, res = best_time(lambda: solver.solve(ivp), repeats)
            n_f = res.stats["n_f_evals"]
            x, total, largest = res.ys, int(n_f.sum()), int(n_f.max())
            success = bool((res.status == 0).all())
        else:
            raise ValueError(f"unknown solver {name!r}")
    return {
        "solver": ADAPTIVE_SOLVERS[name],
        "t_end": problem["t_end"],
        "rtol": float(rtol),
        "atol": float(atol),
        "wall_s": wall,
        "batched_f_calls": calls["n"] // repeats,
        "sample_f_evals": total,
        "max_sample_f_evals": largest,
        "max_error": float(np.abs(x.numpy() - ref).max()),
        "all_success": success,
    }


def match_error(runs, target):
    """The cost of one solver at max error ``target``, read off its tolerance sweep.

    The successful ``runs`` are ordered from the loosest rtol to the tightest; the first
    consecutive pair whose errors bracket the target (looser error >= target >= tighter error)
    is used, and rtol, f-evaluations, batched calls and wall time are interpolated linearly in
    log-log against log(error) between the two runs. Taking the first (loosest) bracket gives
    the cheapest crossing where the error is not monotone in rtol. Nothing is extrapolated:
    None when no pair brackets the target.
    """
    ok = sorted((r for r in runs if r["all_success"]), key=lambda r: -r["rtol"])
    for loose, tight in zip(ok[:-1], ok[1:], strict=True):
        e_loose, e_tight = loose["max_error"], tight["max_error"]
        if not e_loose >= target >= e_tight:
            continue
        w = 0.0 if e_loose == e_tight else math.log(e_loose / target) / math.log(e_loose / e_tight)

        def geo(key, loose=loose, tight=tight, w=w):
            if w in (0.0, 1.0):  # the target is one run's error: that run, exactly
                return float(tight[key] if w else loose[key])
            return math.exp((1 - w) * math.log(loose[key]) + w * math.log(tight[key]))

        return {
            "rtol": geo("rtol"),
            "rtol_looser": loose["rtol"],
            "rtol_tighter": tight["rtol"],
            "error_looser": e_loose,
            "error_tighter": e_tight,
            "sample_f_evals": geo("sample_f_evals"),
            "batched_f_calls": geo("batched_f_calls"),
            "wall_s": geo("wall_s"),
        }
    return None


def adaptive_tables(
    batch,
    t_end,
    n_out,
    rtols,
    mu_max,
    seed,
    repeats=1,
    base_rtol=1e-6,
    atol_ratio=1e-3,
    max_extend=4,
    max_refine=2,
    close=1.25,
):
    """dopri5 on a batch of Van der Pol oscillators with spread mu: equal rtol and matched error.

    1. Grid: every solver runs the geometric grid ``rtols`` (``base_rtol`` is added if
       missing), with ``atol = atol_ratio * rtol`` for all solvers (1e-9 at rtol 1e-6).
    2. Target: the max error that ours reaches at ``base_rtol`` (the run the issue names).
    3. Extension: a solver whose sweep does not bracket the target (its loosest run already
       beats it, or its tightest run misses it) gets further points of the grid's ratio on
       that side, at most ``max_extend`` of them.
    4. Matching and refinement: :func:`match_error` interpolates the solver's sweep at the
       target; the solver is then run at the interpolated rtol (the check run). While the
       check run's error is off the target by more than the factor ``close``, it joins the
       sweep and the interpolation is redone, at most ``max_refine`` times. The matched row
       reports the last interpolation and the error and f-evaluations of its check run, so a
       reader sees how well the interpolation holds. All runs time ``repeats`` calls.

    Returns:
        dict with ``equal`` (the runs at ``base_rtol``, one per solver), ``sweep`` (every run,
        with ``kind``: grid, extension, refinement or check) and ``matched`` (one row per solver at
        the target error; ``*_vs_<peer>`` is this solver's value over the peer's, for the
        summed per-sample f-evaluations, the batched f calls and the wall time).
    """
    problem = _adaptive_problem(batch, t_end, n_out, mu_max, seed)
    grid = sorted({float(r) for r in rtols} | {float(base_rtol)}, reverse=True)
    if len(grid) < 2:
        raise ValueError("the sweep needs at least two tolerances")
    step = (grid[0] / grid[-1]) ** (1.0 / (len(grid) - 1))
    runs = {name: [] for name in ADAPTIVE_SOLVERS}

    def run(name, rtol, kind):
        row = run_dopri5(name, problem, rtol, atol_ratio * rtol, repeats)
        row["kind"] = kind
        runs[name].append(row)
        return row

    cases = [(rtol, name) for rtol in grid for name in ADAPTIVE_SOLVERS]
    for rtol, name in progress(cases, f"dopri5 runs, T = {t_end:g} (rtol x solver)"):
        run(name, rtol, "grid")
    equal = {
        name: next(r for r in rows if r["rtol"] == float(base_rtol)) for name, rows in runs.items()
    }
    target = equal["ours"]["max_error"]
    matched = {}
    for name, rows in runs.items():
        for _ in range(max_extend):
            ok = sorted((r for r in rows if r["all_success"]), key=lambda r: -r["rtol"])
            if not ok:
                break
            if ok[0]["max_error"] < target:
                new = max(r["rtol"] for r in rows) * step
            elif ok[-1]["max_error"] > target:
                new = min(r["rtol"] for r in rows) / step
            else:
                break
            if not 1e-13 <= new <= 1e-2:
                break
            run(name, new, "extension")
        row = {"solver": ADAPTIVE_SOLVERS[name], "t_end": t_end, "target_error": target}
        m, check = None, None
        for attempt in range(max_refine + 1):
            m = match_error(rows, target)
            if m is None:
                break
            check = next((r for r in rows if r["rtol"] == m["rtol"]), None)
            if check is not None:  # the target is one run's error: that run is the check
                break
            check = run_dopri5(name, problem, m["rtol"], atol_ratio * m["rtol"], repeats)
            if attempt == max_refine or abs(math.log(check["max_error"] / target)) <= math.log(
                close
            ):
                break
            check["kind"] = "refinement"
            rows.append(check)
        row["bracketed"] = m is not None
        if check is not None and "kind" not in check:  # the final check run, for the record
            check["kind"] = "check"
            rows.append(check)
        if m is not None:
            row.update(m)
            row["check_max_error"] = check["max_error"]
            row["check_sample_f_evals"] = check["sample_f_evals"]
            row["check_wall_s"] = check["wall_s"]
        matched[name] = row
    for row in matched.values():
        for peer in ("torchdiffeq", "torchode"):
            other = matched[peer]
            for key, short in (
                ("sample_f_evals", "f_evals"),
                ("batched_f_calls", "batched_calls"),
                ("wall_s", "wall"),
            ):
                ratio = None
                if row["bracketed"] and other["bracketed"]:
                    ratio = row[key] / other[key]
                row[f"{short}_vs_{peer}"] = ratio
    columns = [
        "solver",
        "t_end",
        "target_error",
        "rtol",
        "rtol_looser",
        "rtol_tighter",
        "sample_f_evals",
        "batched_f_calls",
        "wall_s",
        "f_evals_vs_torchdiffeq",
        "f_evals_vs_torchode",
        "batched_calls_vs_torchdiffeq",
        "batched_calls_vs_torchode",
        "wall_vs_torchdiffeq",
        "wall_vs_torchode",
        "check_max_error",
        "check_sample_f_evals",
        "check_wall_s",
        "error_looser",
        "error_tighter",
        "bracketed",
    ]
    matched_rows = [{key: row.get(key) for key in columns} for row in matched.values()]
    equal_rows = [
        {key: value for key, value in row.items() if key not in ("rtol", "atol", "kind")}
        for row in equal.values()
    ]
    sweep = [row for rows in runs.values() for row in sorted(rows, key=lambda r: -r["rtol"])]
    return {"equal": equal_rows, "sweep": sweep, "matched": matched_rows}


def work_precision_figure(sweep, matched, path):
    """Max error against summed f-evaluations, batched f calls and wall time, per solver.

    One row of panels per t_end; each solver's sweep runs joined in rtol order (refinement
    and check runs included), stars at the matched-error interpolation, a dotted line at the
    target error.
    """
    t_ends = list(dict.fromkeys(r["t_end"] for r in sweep))
    panels = (
        ("sample_f_evals", "f-evaluations summed over samples (solvers' counters)"),
        ("batched_f_calls", "batched f calls"),
        ("wall_s", "wall time [s]"),
    )
    fig, axes = plt.subplots(
        len(t_ends), len(panels), figsize=(14, 3.8 * len(t_ends)), squeeze=False
    )
    for ax_row, t_end in zip(axes, t_ends, strict=True):
        target = next(r["target_error"] for r in matched if r["t_end"] == t_end)
        for i, label in enumerate(ADAPTIVE_SOLVERS.values()):
            rows = sorted(
                (r for r in sweep if r["t_end"] == t_end and r["solver"] == label),
                key=lambda r: -r["rtol"],
            )
            m = next(r for r in matched if r["t_end"] == t_end and r["solver"] == label)
            for ax, (key, _) in zip(ax_row, panels, strict=True):
                ax.plot(
                    [r[key] for r in rows],
                    [r["max_error"] for r in rows],
                    "o-",
                    color=f"C{i}",
                    label=label,
                )
                if m["bracketed"]:
                    ax.plot(m[key], target, "*", color=f"C{i}", markersize=12)
        for ax, (_, xlabel) in zip(ax_row, panels, strict=True):
            ax.axhline(target, color="gray", linestyle=":", linewidth=1)
            ax.set_xscale("log")
            ax.set_yscale("log")
            readable_log_ticks(ax.xaxis)  # the wall times may span less than a decade
            readable_log_ticks(ax.yaxis)
            ax.set_xlabel(xlabel, fontsize=8)
            ax.set_ylabel("max error")
            ax.set_title(f"t_end = {t_end:g}; stars: matched target error", fontsize=9)
        ax_row[0].legend(fontsize=7, loc="best")
    return save_figure(fig, path)


QUICK_RTOLS = (1e-5, 1e-6, 1e-7)
FULL_RTOLS = tuple(10.0 ** (-k / 2) for k in range(10, 15))  # 1e-5 ... 1e-7, half decades


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, "bench_explicit")
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        if args.quick:
            fixed = fixed_step_table([1, 64], 100, 1, False, args.seed)
            n_osc = 16
            studies = [adaptive_tables(n_osc, 2.0, 11, QUICK_RTOLS, 20.0, args.seed, max_extend=2)]
        else:
            fixed = fixed_step_table([1, 1024, 65536], 1000, 3, not args.no_compile, args.seed)
            n_osc = 256
            studies = [
                adaptive_tables(n_osc, t_end, 101, FULL_RTOLS, 20.0, args.seed, repeats=3)
                for t_end in (10.0, 20.0)
            ]
        adaptive = [row for study in studies for row in study["equal"]]
        matched = [row for study in studies for row in study["matched"]]
        sweep = [row for study in studies for row in study["sweep"]]
        header = (
            f"Measured {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC on "
            f"{platform.machine()} ({platform.processor() or 'cpu'}), torch {torch.__version__}, "
            "1 thread, float64.\n\n"
        )
        md_fixed = write_table(fixed, out / "fixed_step_rk4")
        md_adaptive = write_table(adaptive, out / "adaptive_dopri5")
        md_matched = write_table(matched, out / "adaptive_dopri5_matched")
        md_sweep = write_table(sweep, out / "adaptive_dopri5_sweep")
        work_precision_figure(sweep, matched, out / "adaptive_dopri5_work_precision.png")
        report = (
            header
            + "## Fixed-step RK4, Van der Pol (mu = 1), h = 0.01\n\n"
            + md_fixed
            + f"\n## dopri5, {n_osc} Van der Pol oscillators, mu in [0.1, 20], "
            "rtol 1e-6, atol 1e-9\n\n"
            + md_adaptive
            + "\n## dopri5 at matched error (target: ours' max error at rtol 1e-6)\n\n"
            + "Sweep of rtol with atol = 1e-3 rtol for every solver; rtol, f-evaluations, "
            "batched calls and wall time interpolated log-log in the error between the loosest "
            "pair of runs that brackets the target; check_* is a run at the interpolated rtol; "
            "*_vs_<peer> is this solver's value over the peer's. Summed f-evaluations are the "
            "solvers' own counters (ours: samples still integrating; torchode and "
            "torchdiffeq: batched calls x batch); batched f calls count model work alike.\n\n"
            + md_matched
            + "\n## dopri5 tolerance sweep\n\n"
            + md_sweep
        )
        (out / "bench_explicit.md").write_text(report)
        fig, ax = plt.subplots(figsize=(7, 4))
        solvers = list(dict.fromkeys(r["solver"] for r in fixed))
        batches = list(dict.fromkeys(r["batch"] for r in fixed))
        for name in solvers:
            walls = [
                next(r["wall_s"] for r in fixed if r["solver"] == name and r["batch"] == b)
                for b in batches
            ]
            ax.loglog(batches, walls, "o-", label=name)
        ax.set_xticks(batches, [str(b) for b in batches])
        ax.minorticks_off()
        ax.set_xlabel("batch size")
        ax.set_ylabel("wall time [s]")
        ax.legend(fontsize=7)
        save_figure(fig, out / "fixed_step_rk4.png")
        finish(out, report)
        return {"fixed": fixed, "adaptive": adaptive, "matched": matched, "sweep": sweep}
    finally:
        torch.set_num_threads(previous_threads)


if __name__ == "__main__":
    main()
