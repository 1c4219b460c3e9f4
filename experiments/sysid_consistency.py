"""Bias and variance vs N: ARX least squares vs OE Gauss-Newton (notes §4.6.2-4.6.4).

True system ``y = B/F u + v`` with ``B = 0.5 q^-1 + 0.3 q^-2``, ``F = 1 - 1.2 q^-1 + 0.5 q^-2``.
Three Monte-Carlo studies per record length N (each one batched call over all trials):

* ``arx_ls / equation``: equation-error noise ``F y = B u + e`` (the ARX noise model,
  eq. 4.117-4.120): least squares (eq. 4.111-4.112) is consistent (no bias);
* ``arx_ls / output``: white output noise ``y = B/F u + e``: the equation error ``F e`` is
  coloured and correlated with the regressors, so least squares is biased and the bias does
  NOT shrink with N;
* ``oe_gn / output``: the OE model fitted by Gauss-Newton on the simulation error on the same
  output-noise data: consistent, standard deviation falling like 1/sqrt(N);
* ``arx_iv / output``: instrumental variables on the same data (consistent, less efficient).

Results go to ``consistency.csv``, rewritten atomically after each N, so a rerun resumes
where the last one stopped; on resume, rows that cannot be parsed and record lengths with
fewer than all four estimator rows are dropped (with a message) and recomputed. The figure
shows |bias| and std of the a1/f1 coefficient vs N with the fitted log-log slopes.

Run: ``python -m experiments.sysid_consistency [--quick] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import csv
import io
import math

from experiments._common import (
    atomic_write_text,
    experiment_parser,
    finish,
    output_dir,
    parse_early,
    progress,
    readable_log_ticks,
    save_figure,
    write_table,
)

NAME = "sysid_consistency"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=200, help="Monte-Carlo data sets per N")
    parser.add_argument("--sigma", type=float, default=0.5, help="noise standard deviation")
    parser.add_argument(
        "--ns",
        type=int,
        nargs="+",
        default=[250, 500, 1000, 2000, 4000, 8000],
        help="data lengths N",
    )
    return parser


parse_early(__name__, build_parser)

import numpy as np
import torch

from experiments._common import plt
from sysid import ARX, OE, fit
from sysid.montecarlo import input_signal, simulate_data, summarize_estimates

B_TRUE = [0.5, 0.3]
F_TRUE = [-1.2, 0.5]
FIELDS = [
    "N",
    "trials",
    "sigma",
    "estimator",
    "noise",
    "bias_f1",
    "std_f1",
    "bias_se_f1",
    "bias_norm",
    "rms_std",
    "mse",
    "converged",
]
CASES = [("arx_ls", "equation"), ("arx_ls", "output"), ("arx_iv", "output"), ("oe_gn", "output")]


def run_n(N: int, trials: int, sigma: float, seed: int) -> list[dict]:
    """One record length: all estimators, each in one batched call."""
    g = torch.Generator().manual_seed(seed)
    th_oe = torch.tensor(B_TRUE + F_TRUE, dtype=torch.float64)
    th_arx = torch.tensor(F_TRUE + B_TRUE, dtype=torch.float64)
    u = input_signal("white", N, (trials,), generator=g)
    eq_data = simulate_data(
        ARX(2, 2, 1), u, theta=th_arx, noise_std=sigma, noise="model", generator=g
    )
    out_data = simulate_data(OE(2, 2, 1), u, theta=th_oe, noise_std=sigma, generator=g)
    cases = [
        ("arx_ls", "equation", fit(ARX(2, 2, 1), eq_data), th_arx, 0),
        ("arx_ls", "output", fit(ARX(2, 2, 1), out_data), th_arx, 0),
        ("arx_iv", "output", fit(ARX(2, 2, 1), out_data, method="iv"), th_arx, 0),
        ("oe_gn", "output", fit(OE(2, 2, 1), out_data), th_oe, 2),
    ]
    rows = []
    for name, noise, res, truth, i_f1 in cases:
        s = summarize_estimates(res.theta, truth)
        rows.append(
            {
                "N": N,
                "trials": trials,
                "sigma": sigma,
                "estimator": name,
                "noise": noise,
                "bias_f1": s.bias[i_f1].item(),
                "std_f1": s.std[i_f1].item(),
                "bias_se_f1": s.bias_standard_error[i_f1].item(),
                "bias_norm": torch.linalg.norm(s.bias).item(),
                "rms_std": s.std.pow(2).mean().sqrt().item(),
                "mse": s.mse.item(),
                "converged": res.converged.double().mean().item(),
            }
        )
    return rows


def _parse(row: dict) -> dict | None:
    """A CSV row with its numbers converted, or None where a field is missing or unparsable
    (e.g. the half-written last line of an interrupted run)."""
    if None in row or any(row.get(k) in (None, "") for k in FIELDS):
        return None
    try:
        out = {k: (row[k] if k in ("estimator", "noise") else float(row[k])) for k in FIELDS}
        out["N"], out["trials"] = int(row["N"]), int(row["trials"])
    except ValueError:
        return None
    return out if (out["estimator"], out["noise"]) in CASES else None


def _load(path) -> list[dict]:
    """The complete record lengths of ``path``: every row that parses, of every
    ``(N, trials, sigma)`` that has exactly one row per estimator case; the rest is dropped
    with a message (and recomputed by the caller)."""
    if not path.exists():
        return []
    with open(path, newline="") as handle:
        raw = list(csv.DictReader(handle))
    rows = [r for r in map(_parse, raw) if r is not None]
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["N"], r["trials"], r["sigma"]), []).append(r)
    keep = []
    for key, group in groups.items():
        if sorted((r["estimator"], r["noise"]) for r in group) == sorted(CASES):
            keep += group
        else:
            print(
                f"{path}: N = {int(key[0])} has {len(group)} of {len(CASES)} rows; recomputing it"
            )
    if len(rows) < len(raw):
        print(f"{path}: dropped {len(raw) - len(rows)} unreadable row(s) (interrupted write?)")
    return keep


def _save(path, rows: list[dict]) -> None:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=FIELDS)
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_text(path, buffer.getvalue())


def loglog_slope(ns, values) -> float:
    """Least-squares slope of log(values) vs log(N)."""
    return float(np.polyfit(np.log(ns), np.log(np.abs(values)), 1)[0])


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    trials = 60 if args.quick else args.trials
    ns = [200, 800] if args.quick else args.ns
    partial = out / "consistency.csv"
    done = _load(partial)
    have = {int(r["N"]) for r in done if int(r["trials"]) == trials and r["sigma"] == args.sigma}
    # resumable: the file holds every finished N, rewritten atomically
    for N in progress(ns, "data lengths N"):
        if N in have:
            continue
        done += run_n(N, trials, args.sigma, seed=N)
        _save(partial, done)
    _save(partial, done)  # also clears rows dropped on loading
    rows = [
        r
        for r in done
        if int(r["trials"]) == trials and r["sigma"] == args.sigma and int(r["N"]) in ns
    ]
    rows.sort(key=lambda r: (r["estimator"], r["noise"], r["N"]))
    summary = []
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for (name, noise), style in zip(CASES, ["o-", "s-", "^-", "d-"], strict=True):
        sel = [r for r in rows if r["estimator"] == name and r["noise"] == noise]
        if not sel:
            continue
        n = np.array([r["N"] for r in sel])
        bias = np.array([abs(r["bias_f1"]) for r in sel])
        std = np.array([r["std_f1"] for r in sel])
        label = f"{name} ({noise} noise)"
        axes[0].loglog(n, bias, style, label=label)
        axes[1].loglog(n, std, style, label=label)
        summary.append(
            {
                "estimator": name,
                "noise": noise,
                "bias_f1_at_min_N": sel[0]["bias_f1"],
                "bias_f1_at_max_N": sel[-1]["bias_f1"],
                "bias_over_se_at_max_N": abs(sel[-1]["bias_f1"]) / sel[-1]["bias_se_f1"],
                "std_slope": loglog_slope(n, std) if len(n) > 1 else math.nan,
            }
        )
    n_all = np.array(sorted({r["N"] for r in rows}))
    axes[1].loglog(n_all, rows[0]["std_f1"] * np.sqrt(n_all[0] / n_all), "k:", label="1/sqrt(N)")
    axes[0].set_title("|bias| of a1 (ARX) / f1 (OE)")
    axes[1].set_title("standard deviation of a1 / f1")
    axes[0].set_ylabel("|mean estimate - true value|")
    axes[1].set_ylabel("standard deviation over the data sets")
    for ax in axes:
        ax.set_xlabel("N (samples)")
        ax.set_xticks(n_all, [str(n) for n in n_all])  # one label per data length, no minor labels
        ax.minorticks_off()
        readable_log_ticks(ax.yaxis)
        ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out / "consistency.png")
    write_table(rows, out / "consistency_table")
    markdown = write_table(summary, out / "consistency_summary")
    (out / "README.md").write_text(f"# {NAME}\n\n{__doc__}\n\n{markdown}")
    finish(out, markdown)
    return summary


if __name__ == "__main__":
    main()
