"""Benchmark: gradient of the output-error simulation loss through three IIR filters.

Task (issue 4): OE model ``y = q^-1 B(q)/F(q) u`` with nb = nf = 4, loss
``sum_t (y_t - yhat_t)^2``, gradient with respect to the 8 parameters, on N samples
(100 000 in the full run). Three implementations, run side by side in one process:

- ``ours``: :class:`sysid.OE` ``simulation_errors`` through :func:`sysid.filters.iir_filter`
  (one autograd node, adjoint backward; on the CPU with one shared filter its two filtering
  passes run in ``scipy.signal.lfilter`` by default, elsewhere in the block-Toeplitz method);
- ``ours_torch``: the same with the pure-torch block method forced on the CPU
  (``sysid.filters.cpu_backend("torch")``; the path used on CUDA, for batched coefficients
  and for higher derivatives), so that the comparison of the torch code itself stays visible;
- ``scipy_autograd``: a dynoNet-style :class:`torch.autograd.Function` calling
  ``scipy.signal.lfilter`` in forward and backward (CPU, zero initial conditions; written here
  for the comparison only, it is not part of the library);
- ``python_loop``: the recursion ``y_k = sum b_j x_{k-j} - sum a_i y_{k-i}`` written as a
  Python loop over samples, differentiated by autograd.

All three reach the same loss and gradient (the relative differences are in the table).
Our :class:`IOData` and :class:`OE` model are built once outside the timed loop, as in a fit
(building the model costs about 0.1 ms, 3 % of one gradient at N = 100 000).
A last case runs a batch of data sets (2000 of N = 1000 in the full run): ours in one batched
call (one model with ``batch_shape=(2000,)``) vs the scipy function in a loop over data sets.
``--quick`` uses short signals and 50 data sets. Timings are the best of ``--repeats`` runs,
wall clock and process CPU time (on a shared machine the CPU time is the fairer measure).
The estimators' ``experiments/bench_sysid.py`` may import
:func:`oe_gradient`, :class:`ScipyLFilter` and :func:`loop_lfilter` from here.
"""

from __future__ import annotations

import argparse
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

NAME = "bench_filter"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument(
        "--N", type=int, default=None, help="signal length (default 100000, 2000 with --quick)"
    )
    parser.add_argument(
        "--repeats",
        type=int,
        default=None,
        help="best of this many runs (default 5, 3 with --quick)",
    )
    parser.add_argument(
        "--threads", type=int, default=1, help="torch CPU threads (scipy runs on one)"
    )
    return parser


parse_early(__name__, build_parser)

import numpy as np
import scipy.signal
import torch

from experiments._common import plt
from sysid import OE, IOData
from sysid.filters import cpu_backend

NB = NF = 4


class ScipyLFilter(torch.autograd.Function):
    """``y = B(q)/A(q) x`` with scipy's lfilter in forward and backward (dynoNet style).

    ``b`` ``(m,)``, ``a`` ``(n + 1,)`` with ``a[0] = 1``, ``x`` ``(*batch, N)``, zero initial
    conditions. Backward: ``z = A^-T g`` (scipy on the reversed gradient), then
    ``dL/dx = B^T z``, ``dL/db_j = sum_k z_k x_{k-j}`` and ``dL/da_i = -sum_k z_k y_{k-i}``.
    """

    @staticmethod
    def forward(ctx, b, a, x):
        bn, an, xn = (t.detach().cpu().numpy() for t in (b, a, x))
        y = torch.from_numpy(scipy.signal.lfilter(bn, an, xn, axis=-1)).to(x)
        ctx.save_for_backward(b, a, x, y)
        return y

    @staticmethod
    def backward(ctx, grad_y):
        b, a, x, y = (t.detach().cpu().numpy() for t in ctx.saved_tensors)
        g = grad_y.detach().cpu().numpy()
        z = scipy.signal.lfilter([1.0], a, g[..., ::-1], axis=-1)[..., ::-1]
        N = x.shape[-1]
        grad_x = scipy.signal.lfilter(b, [1.0], z[..., ::-1], axis=-1)[..., ::-1]
        grad_b = np.array([np.sum(z[..., j:] * x[..., : N - j]) for j in range(len(b))])
        grad_a = np.array([0.0] + [-np.sum(z[..., i:] * y[..., : N - i]) for i in range(1, len(a))])
        like = ctx.saved_tensors[2]
        return (
            torch.from_numpy(grad_b).to(like),
            torch.from_numpy(grad_a).to(like),
            torch.from_numpy(np.ascontiguousarray(grad_x)).to(like),
        )


def loop_lfilter(b: torch.Tensor, a: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Naive recursion, a Python loop over samples: ``y_k = sum b_j x_{k-j} - sum a_i y_{k-i}``.

    ``b`` ``(m,)``, ``a`` ``(n + 1,)`` with ``a[0] = 1``, ``x`` ``(N,)``; zero initial state.
    """
    m, n = b.shape[0], a.shape[0] - 1
    xs = torch.cat([x.new_zeros(m - 1), x])
    ys = [x.new_zeros(()) for _ in range(n)]
    for k in range(x.shape[0]):
        acc = (b.flip(0) * xs[k : k + m]).sum()
        if n:
            acc = acc - (a[1:] * torch.stack(ys[-1 : -n - 1 : -1])).sum()
        ys.append(acc)
    return torch.stack(ys[n:])


def make_problem(N: int, seed: int = 0, dtype=torch.float64, batch: tuple = ()):
    """Data from a stable 4th-order OE system (nb = nf = 4, nk = 1) plus white noise.

    Returns ``u, y`` (``(*batch, N)``) and ``theta`` (``(*batch, 8)``, near the truth).
    """
    g = torch.Generator().manual_seed(seed)
    u = torch.randn(*batch, N, generator=g, dtype=dtype)
    f_true = np.poly([0.9, 0.7, 0.5 + 0.4j, 0.5 - 0.4j]).real  # [1, f1..f4]
    b_true = np.array([0.5, 0.3, -0.2, 0.1])
    y = scipy.signal.lfilter(np.r_[0.0, b_true], f_true, u.numpy(), axis=-1)
    y = torch.tensor(y, dtype=dtype) + 0.1 * torch.randn(*batch, N, generator=g, dtype=dtype)
    theta = torch.tensor(np.r_[b_true, f_true[1:]], dtype=dtype) * 0.95  # near the truth
    return u, y, theta.expand(*batch, 2 * NB).clone()


def oe_model(theta: torch.Tensor, u: torch.Tensor) -> OE:
    """The OE(4, 4) model (nk = 1) of ``oe_gradient`` for the batch shape of ``theta``."""
    return OE(NB, NF, nk=1, batch_shape=theta.shape[:-1], dtype=u.dtype, device=u.device)


def oe_gradient(
    method: str, u: torch.Tensor, y: torch.Tensor, theta: torch.Tensor, data=None, model=None
):
    """Loss ``sum (y - B/F u)^2`` and its gradient w.r.t. ``theta = [b1..b4, f1..f4]``.

    ``data``, ``model``: the :class:`IOData` of ``(u, y)`` and the :class:`OE` model for
    ``"ours"``, built (and validated) once, as in a fit; built here when not given.
    """
    if method == "ours_torch":  # the pure-torch block method, no CPU dispatch to scipy
        with cpu_backend("torch"):
            return oe_gradient("ours", u, y, theta, data, model)
    theta = theta.detach().clone().requires_grad_(True)
    if method == "scipy_autograd_loop":  # one scipy call per data set of a batch
        runs = [oe_gradient("scipy_autograd", u[i], y[i], theta[i]) for i in range(len(u))]
        return torch.stack([r[0] for r in runs]).sum(), torch.stack([r[1] for r in runs])
    b, f = theta[:NB], theta[NB:]
    if method == "ours":
        model = model or oe_model(theta, u)
        data = data or IOData(u.unsqueeze(-1), y.unsqueeze(-1))
        residual = model.simulation_errors(data, theta=theta)
    else:
        num = torch.cat([theta.new_zeros(1), b])  # nk = 1
        den = torch.cat([theta.new_ones(1), f])
        sim = ScipyLFilter.apply(num, den, u) if method == "scipy_autograd" else None
        if method == "python_loop":
            sim = loop_lfilter(num, den, u)
        if sim is None:
            raise ValueError(f"unknown method {method!r}")
        residual = y - sim
    loss = (residual**2).sum()
    (grad,) = torch.autograd.grad(loss, theta)
    return loss.detach(), grad


def _time(fn, repeats: int, device: torch.device) -> tuple[float, float, object]:
    """Best-of-``repeats`` wall-clock and process-CPU seconds of ``fn()`` (after a warm-up).

    The minimum is the robust estimate on a shared machine; CPU time (all threads of this
    process) is less sensitive than wall time to other processes competing for the cores.
    """
    result = fn()  # warm-up
    walls, cpus = [], []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize()
        start, start_cpu = time.perf_counter(), time.process_time()
        result = fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        walls.append(time.perf_counter() - start)
        cpus.append(time.process_time() - start_cpu)
    return min(walls), min(cpus), result


def main(argv=None):
    args = build_parser().parse_args(argv)
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(args.threads)
    try:
        return _run(args)
    finally:
        torch.set_num_threads(previous_threads)


def _run(args):
    out = output_dir(args, NAME)
    N = args.N or (2000 if args.quick else 100_000)
    repeats = args.repeats or (3 if args.quick else 5)
    sizes = sorted({N // 100, N // 10, N} - {0})
    devices = [torch.device("cpu")]
    if torch.cuda.is_available():
        devices.append(torch.device("cuda"))

    rows, curves = [], {}
    batch = 50 if args.quick else 2000
    cases = [(n, 1) for n in sizes] + [(200 if args.quick else 1000, batch)]
    for n, n_sets in progress(cases, "signal lengths"):
        shape = () if n_sets == 1 else (n_sets,)
        u, y, theta = make_problem(n, batch=shape)
        if n_sets == 1:
            ref_loss, ref_grad = oe_gradient("scipy_autograd", u, y, theta)
            runs = [("scipy_autograd", "cpu"), ("python_loop", "cpu")]
        else:
            ref_loss, ref_grad = oe_gradient("scipy_autograd_loop", u, y, theta)
            runs = [("scipy_autograd_loop", "cpu")]
        runs += [("ours", d.type) for d in devices] + [("ours_torch", "cpu")]
        timing = {}
        for method, device in runs:
            reps = 1 if method == "python_loop" else repeats
            u_d, y_d, theta_d = (t.to(device) for t in (u, y, theta))
            data = IOData(u_d.unsqueeze(-1), y_d.unsqueeze(-1))  # validated once, as in a fit
            model = oe_model(theta_d, u_d)  # built once, as in a fit

            def run(m=method, u_d=u_d, y_d=y_d, theta_d=theta_d, data=data, model=model):
                return oe_gradient(m, u_d, y_d, theta_d, data=data, model=model)

            wall, cpu, (loss, grad) = _time(run, reps, torch.device(device))
            label = method if device == "cpu" else f"{method}_{device}"
            timing[label] = (wall, cpu)
            if n_sets == 1:
                curves.setdefault(label, []).append((n, wall))
            rows.append(
                {
                    "N": n,
                    "data_sets": n_sets,
                    "method": label,
                    "threads": args.threads,
                    "seconds": wall,
                    "cpu_seconds": cpu,
                    "loss_rel_diff": abs(float(loss) - float(ref_loss)) / abs(float(ref_loss)),
                    "grad_rel_diff": float((grad.cpu() - ref_grad).norm() / ref_grad.norm()),
                }
            )
        for row in rows:
            if (row["N"], row["data_sets"]) == (n, n_sets):
                row["speedup_of_ours"] = row["seconds"] / timing["ours"][0]
                row["cpu_speedup_of_ours"] = row["cpu_seconds"] / timing["ours"][1]

    markdown = write_table(rows, out / NAME)
    fig, ax = plt.subplots(figsize=(5.5, 4))
    for label, pts in curves.items():
        ns, ts = zip(*pts, strict=True)
        ax.loglog(ns, ts, "o-", label=label)
    ax.set_xlabel("samples N")
    ax.set_ylabel("wall seconds per loss + gradient (best of repeats)")
    ax.set_title(f"OE (nb = nf = {NB}) simulation-error gradient")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    save_figure(fig, out / f"{NAME}.png")
    finish(out, markdown)
    return rows


if __name__ == "__main__":
    main()
