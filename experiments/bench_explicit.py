"""Benchmark: fixed-step RK4 and adaptive dopri5 against torchdiffeq and torchode.

Two tables, one process, one thread, float64, errors against a tight scipy DOP853 reference:

1. Fixed-step RK4 on Van der Pol (mu = 1, notes eq. 6.43), 1000 steps of h = 0.01, batch 1,
   1024 and 65 536: this project (classic RK4 and the 3/8 rule, compiled and eager) against
   torchdiffeq's ``"rk4"`` (which is the 3/8 rule, ``rk4_alt_step_func``) and against
   torchdiffeq's own classic-RK4 step function plugged into its fixed-grid solver. The
   speed-up is torchdiffeq's wall time over ours on the same grid; the one-off compile time
   is reported separately.
2. dopri5 (rtol 1e-6, atol 1e-9) on 256 Van der Pol oscillators with mu spread over
   [0.1, 20]: f-evaluations, wall time and error of this project's per-sample step control
   (``odeint(method="dopri5")``), torchdiffeq's dopri5 (one step size for the batch) and
   torchode's Dopri5 (per-sample step control).

Run: ``python -m experiments.bench_explicit`` (full sizes, minutes) or ``--quick``.
"""

from __future__ import annotations

import datetime
import platform
import time

import numpy as np
import scipy.integrate
import torch

from experiments._common import experiment_parser, output_dir, plt, save_figure, write_table
from integrators import odeint

try:  # contract C6; a local copy keeps the benchmark usable without sysid
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
    for batch in batches:
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


def adaptive_table(batch, t_end, n_out, rtol, atol, mu_max, seed, repeats=1):
    """Rows of the dopri5 comparison on a batch of Van der Pol oscillators with spread mu."""
    import torchdiffeq
    import torchode

    mu = torch.linspace(0.1, mu_max, batch, dtype=torch.float64)[:, None]
    f = van_der_pol(mu)
    gen = torch.Generator().manual_seed(seed)
    x0 = 4 * torch.rand(batch, 2, dtype=torch.float64, generator=gen) - 2
    t = torch.linspace(0.0, t_end, n_out, dtype=torch.float64)
    ref = reference(mu.numpy(), x0.numpy(), t.numpy())
    calls = {"n": 0}

    def counted(t_, x):
        calls["n"] += 1
        return f(t_, x)

    rows = []
    with torch.no_grad():
        calls["n"] = 0
        wall, sol = best_time(
            lambda: odeint(counted, x0, t, method="dopri5", rtol=rtol, atol=atol), repeats
        )
        per_sample = sol.stats.n_f_evals
        rows.append(
            {
                "solver": "ours dopri5 (per-sample steps)",
                "t_end": t_end,
                "wall_s": wall,
                "batched_f_calls": calls["n"] // repeats,
                "sample_f_evals": int(torch.as_tensor(per_sample).sum()),
                "max_sample_f_evals": int(torch.as_tensor(per_sample).max()),
                "max_error": float(np.abs(sol.x.numpy() - ref).max()),
                "all_success": bool(sol.success),
            }
        )

        calls["n"] = 0
        wall, x = best_time(
            lambda: torchdiffeq.odeint(counted, x0, t, method="dopri5", rtol=rtol, atol=atol),
            repeats,
        )
        rows.append(
            {
                "solver": "torchdiffeq dopri5 (one step for the batch)",
                "t_end": t_end,
                "wall_s": wall,
                "batched_f_calls": calls["n"] // repeats,
                "sample_f_evals": calls["n"] // repeats * batch,
                "max_sample_f_evals": calls["n"] // repeats,
                "max_error": float(np.abs(x.transpose(0, 1).numpy() - ref).max()),
                "all_success": True,
            }
        )

        calls["n"] = 0
        term = torchode.ODETerm(counted)
        step = torchode.Dopri5(term=term)
        control = torchode.IntegralController(atol=atol, rtol=rtol, term=term)
        solver = torchode.AutoDiffAdjoint(step, control)
        problem = torchode.InitialValueProblem(y0=x0, t_eval=t.expand(batch, -1))
        wall, res = best_time(lambda: solver.solve(problem), repeats)
        n_f = res.stats["n_f_evals"]
        rows.append(
            {
                "solver": "torchode Dopri5 (per-sample steps)",
                "t_end": t_end,
                "wall_s": wall,
                "batched_f_calls": calls["n"] // repeats,
                "sample_f_evals": int(n_f.sum()),
                "max_sample_f_evals": int(n_f.max()),
                "max_error": float(np.abs(res.ys.numpy() - ref).max()),
                "all_success": bool((res.status == 0).all()),
            }
        )
    return rows


def main(argv=None):
    parser = experiment_parser(
        "bench_explicit",
        "Fixed-step RK4 and adaptive dopri5 against torchdiffeq and torchode (Van der Pol).",
    )
    parser.add_argument("--no-compile", action="store_true", help="skip torch.compile runs")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    out = output_dir(args, "bench_explicit")
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        if args.quick:
            fixed = fixed_step_table([1, 64], 100, 1, False, args.seed)
            adaptive = adaptive_table(16, 2.0, 11, 1e-6, 1e-9, 20.0, args.seed)
        else:
            fixed = fixed_step_table([1, 1024, 65536], 1000, 3, not args.no_compile, args.seed)
            adaptive = [
                row
                for t_end in (10.0, 20.0)
                for row in adaptive_table(256, t_end, 101, 1e-6, 1e-9, 20.0, args.seed, repeats=3)
            ]
        header = (
            f"Measured {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC on "
            f"{platform.machine()} ({platform.processor() or 'cpu'}), torch {torch.__version__}, "
            "1 thread, float64.\n\n"
        )
        md_fixed = write_table(fixed, out / "fixed_step_rk4")
        md_adaptive = write_table(adaptive, out / "adaptive_dopri5")
        report = (
            header
            + "## Fixed-step RK4, Van der Pol (mu = 1), h = 0.01\n\n"
            + md_fixed
            + "\n## dopri5, 256 Van der Pol oscillators, mu in [0.1, 20]\n\n"
            + md_adaptive
        )
        (out / "bench_explicit.md").write_text(report)
        fig, ax = plt.subplots(figsize=(7, 4))
        solvers = list(dict.fromkeys(r["solver"] for r in fixed))
        batches = list(dict.fromkeys(r["batch"] for r in fixed))
        width = 0.8 / len(solvers)
        for i, name in enumerate(solvers):
            walls = [
                next(r["wall_s"] for r in fixed if r["solver"] == name and r["batch"] == b)
                for b in batches
            ]
            ax.bar(np.arange(len(batches)) + i * width, walls, width, label=name)
        ax.set_xticks(np.arange(len(batches)) + 0.4 - width / 2, [str(b) for b in batches])
        ax.set_yscale("log")
        ax.set_xlabel("batch size")
        ax.set_ylabel("wall time [s]")
        ax.legend(fontsize=7)
        save_figure(fig, out / "fixed_step_rk4.png")
        print(report)
        return {"fixed": fixed, "adaptive": adaptive}
    finally:
        torch.set_num_threads(previous_threads)


if __name__ == "__main__":
    main()
