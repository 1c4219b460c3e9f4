"""Benchmark: implicit Runge-Kutta (Radau IIA, Gauss-Legendre) against scipy and torchdiffeq,
and implicit-function-theorem gradients against unrolled Newton iterations.

1. Stiff Van der Pol ``y1' = y2, y2' = ((1 - y1^2) y2 - y1) / eps``, ``y(0) = (2, 0)``,
   ``t in [0, 2]`` (``eps = 1e-6``): adaptive Radau IIA (s = 3, ``solve_implicit_ode``) vs
   ``scipy.integrate.solve_ivp(method="Radau")`` at the same rtol = atol, for one trajectory
   and for a batch of trajectories with different ``eps`` (scipy in a Python loop, ours one
   batched call with per-sample step sizes; ours without gradient recording, in
   ``torch.no_grad()``, as scipy computes no gradients). Errors are relative to scipy Radau at
   rtol = atol = 1e-12 (``--quick``: 1e-10), at the final time, max over components (and
   over the checked members of the batch).
2. Fixed step on the non-stiff Van der Pol (mu = 1, t in [0, 10], dt = 0.01, notes Fig. 7.3):
   Gauss-Legendre s = 2 and Radau IIA s = 3 vs torchdiffeq's only implicit fixed-grid solver,
   ``"implicit_adams"`` (an Adams-Bashforth-Moulton predictor-corrector; torchdiffeq ships no
   implicit Runge-Kutta), at equal step: error vs scipy DOP853 (rtol 1e-13), wall time of
   the forward pass and of forward + backward (gradient of ``|x(T)|^2`` w.r.t. ``x0``, ``mu``).
   Ours runs with the Newton stopping scale ``rtol = 1e-8, atol = 1e-11``, tight enough that
   the error is the method's, not the stage solve's (at the default ``rtol = 1e-6`` Gauss s = 2
   stops its simplified Newton at 1.4e-8, above its discretisation error of 1e-9).

3. Implicit-function-theorem gradients vs unrolled autograd through the Newton iterations
   (forward + backward of a scalar loss, same problem, same iterations where possible):

   a. Van der Pol, batch of ``mu in [0.5, 1.5]``, fixed step (dt = 0.01, t in [0, 10];
      ``--quick``: dt = 0.05, t in [0, 1]), Gauss-Legendre s = 2 and Radau IIA s = 3:
      ``solve_implicit_ode(..., adaptive=False)`` (simplified Newton without a graph, then
      one IFT solve per step, eq. 3.40) vs :func:`unrolled_irk`, the same method written
      plainly (eq. 7.14-7.18, full Newton, autograd on through every iteration and through
      the Newton matrix). Loss ``sum |x(T)|^2``, gradients w.r.t. ``x0`` and ``mu``.
   b. ``integrators.newton`` (full Newton + IFT) vs :func:`unrolled_newton` (the same
      iteration with autograd through it) on ``exp(x) + M x = b`` (n = 8, a batch of ``b``),
      started at ``x0 = L`` so that larger ``L`` forces more iterations (about ``L + 5``):
      the IFT graph keeps the same size while the unrolled graph grows linearly.

   Columns: ``*_saved_MB``, the bytes of distinct storages the autograd graph holds for
   backward at the end of the forward pass (:class:`GraphMemory`, via
   ``torch.autograd.graph.saved_tensors_hooks``: deterministic and available on CPU);
   ``*_cuda_peak_MB`` (only with ``--device cuda``), ``torch.cuda.max_memory_allocated``
   above the start over forward + backward; ``memory_ratio`` = unrolled / IFT saved bytes;
   ``grad_rel_diff`` = ``max|g_IFT - g_unrolled| / max|g_unrolled|`` over the parameters;
   ``*_fd_error``, the relative error of the directional derivative along ``mu`` (3a) or
   ``b`` (3b) against a central finite difference; ``*_newton_iters``, Newton iterations
   per step (3a, mean) or per solve (3b, max over the batch); errors are against scipy
   DOP853 (3a) or ``max ||phi(x)||_inf`` (3b).

All peers run in this process, on one torch thread (``--threads``); times are the best of
``--repeats`` runs. ``--sections`` picks sections (e.g. ``--sections 3``). Results: table
``bench_implicit.csv/.md``, figures ``bench_implicit.png`` (wall times) and
``bench_implicit_ift_memory.png`` (saved memory against Newton iterations, section 3b).
"""

from __future__ import annotations

import argparse
import time

from experiments._common import (
    experiment_parser,
    finish,
    note,
    output_dir,
    parse_early,
    readable_log_ticks,
    save_figure,
    write_table,
)

NAME = "bench_implicit"
#: Progress lines of the study's sections (see above).
SECTIONS = {
    1: "section 1: stiff Van der Pol, adaptive Radau IIA against scipy",
    2: "section 2: fixed-step implicit RK on the non-stiff Van der Pol",
    3: "section 3: implicit-function-theorem gradients against unrolled autograd",
}


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.split("\n\n")[0])
    parser.add_argument(
        "--repeats", type=int, default=3, help="timings are the best of this many runs"
    )
    parser.add_argument("--batch", type=int, default=256, help="trajectories in the batch case")
    parser.add_argument(
        "--batch-rtols",
        type=float,
        nargs="+",
        default=[1e-6, 1e-9],
        help="tolerances of the batch case (scipy's loop at 1e-9 takes long)",
    )
    parser.add_argument(
        "--sections",
        type=int,
        nargs="+",
        choices=(1, 2, 3),
        default=[1, 2, 3],
        help="sections of the study to run (see above)",
    )
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument(
        "--device",
        default=None,
        help="device of section 3 (default cuda when available, else cpu; adds CUDA peak memory)",
    )
    return parser


parse_early(__name__, build_parser)

import numpy as np
import torch
from scipy.integrate import solve_ivp

from experiments._common import plt
from experiments._graph_memory import GraphMemory, with_large_stack
from integrators import gauss_legendre, newton, radau_iia, solve_implicit_ode


def _timed(fn, repeats):
    best, out = float("inf"), None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - start)
    return best, out


def _vdp_scipy(eps, t_end, rtol):
    def rhs(t, y):
        return [y[1], ((1 - y[0] ** 2) * y[1] - y[0]) / eps]

    def jac(t, y):
        return [[0.0, 1.0], [(-2 * y[0] * y[1] - 1) / eps, (1 - y[0] ** 2) / eps]]

    sol = solve_ivp(rhs, (0.0, t_end), [2.0, 0.0], method="Radau", rtol=rtol, atol=rtol, jac=jac)
    return sol.y[:, -1]


def _vdp_torch(eps):
    def rhs(t, y):
        y1, y2 = y[..., 0:1], y[..., 1:2]
        return torch.cat([y2, ((1 - y1**2) * y2 - y1) / eps], -1)

    return rhs


@torch.no_grad()
def stiff_rows(t_end, rtols, batch, n_check, ref_rtol, repeats, batch_rtols=None):
    """Section 1: one trajectory (at ``rtols``) and a batch (at ``batch_rtols``, default
    ``rtols``), ours vs scipy Radau, simulations only (no gradient recording)."""
    batch_rtols = rtols if batch_rtols is None else batch_rtols
    rows = []
    eps_one = 1e-6
    ref_one = _vdp_scipy(eps_one, t_end, ref_rtol)
    eps_batch = np.logspace(-6, -3, batch)
    check = np.unique(np.linspace(0, batch - 1, n_check).round().astype(int))
    ref_batch = np.stack([_vdp_scipy(eps_batch[i], t_end, ref_rtol) for i in check])
    t = torch.tensor([0.0, t_end])
    eps_t = torch.as_tensor(eps_batch)[:, None]
    x0 = torch.tensor([2.0, 0.0]).expand(batch, 2)
    for rtol in rtols:
        ours_t, ours = _timed(
            lambda rtol=rtol: solve_implicit_ode(
                _vdp_torch(eps_one),
                torch.tensor([[2.0, 0.0]]),
                t,
                "radau_iia",
                rtol=rtol,
                atol=rtol,
            ),
            repeats,
        )
        sc_t, sc = _timed(lambda rtol=rtol: _vdp_scipy(eps_one, t_end, rtol), repeats)
        rows.append(
            {
                "case": "stiff VdP eps=1e-6, 1 trajectory",
                "rtol": rtol,
                "ours_error": float(
                    np.max(np.abs(ours.x[0, -1].numpy() - ref_one) / np.abs(ref_one))
                ),
                "peer_error": float(np.max(np.abs(sc - ref_one) / np.abs(ref_one))),
                "ours_s": ours_t,
                "peer": "scipy Radau",
                "peer_s": sc_t,
                "speedup": sc_t / ours_t,
                "ours_steps": int(ours.stats.n_steps.max()),
            }
        )
        if rtol not in batch_rtols:
            continue
        ours_t, ours = _timed(
            lambda rtol=rtol: solve_implicit_ode(
                _vdp_torch(eps_t), x0, t, "radau_iia", rtol=rtol, atol=rtol
            ),
            repeats,  # scipy's loop is timed once: it already sums 256 runs
        )
        start = time.perf_counter()
        sc = np.stack([_vdp_scipy(e, t_end, rtol) for e in eps_batch])
        sc_t = time.perf_counter() - start
        rows.append(
            {
                "case": f"stiff VdP eps in [1e-6, 1e-3], batch {batch}",
                "rtol": rtol,
                "ours_error": float(
                    np.max(np.abs(ours.x[check, -1].numpy() - ref_batch) / np.abs(ref_batch))
                ),
                "peer_error": float(np.max(np.abs(sc[check] - ref_batch) / np.abs(ref_batch))),
                "ours_s": ours_t,
                "peer": "scipy Radau (loop)",
                "peer_s": sc_t,
                "speedup": sc_t / ours_t,
                "ours_steps": int(ours.stats.n_steps.max()),
            }
        )
    return rows


class _VdP(torch.nn.Module):
    def __init__(self, mu):
        super().__init__()
        self.mu = torch.nn.Parameter(torch.tensor(mu))

    def forward(self, t, x):
        return torch.stack([self.mu * (1 - x[..., 1] ** 2) * x[..., 0] - x[..., 1], x[..., 0]], -1)


def _vdp_reference(mu, x0, t_end):
    """x(t_end) of the non-stiff Van der Pol model of sections 2-3 (``_VdP``) by DOP853 at
    rtol = atol = 1e-13: numpy (2,)."""
    return solve_ivp(
        lambda t, x: [mu * (1 - x[1] ** 2) * x[0] - x[1], x[0]],
        (0, t_end),
        x0,
        method="DOP853",
        rtol=1e-13,
        atol=1e-13,
    ).y[:, -1]


def fixed_rows(t_end, dt, repeats):
    """Section 2: fixed-step Gauss / Radau vs torchdiffeq implicit_adams at equal step."""
    import torchdiffeq

    x0_np = np.array([0.5, 1.0])
    ref = _vdp_reference(1.0, x0_np, t_end)
    t = torch.linspace(0.0, t_end, int(round(t_end / dt)) + 1)
    rows = []

    def run(kind, backward):
        model = _VdP(1.0)
        x0 = torch.tensor(x0_np[None], requires_grad=backward)
        with torch.set_grad_enabled(backward):
            if kind == "implicit_adams":
                x = torchdiffeq.odeint(model, x0, t, method="implicit_adams")[-1]
            else:
                method, s = kind
                x = solve_implicit_ode(
                    model, x0, t, method, stages=s, adaptive=False, rtol=1e-8, atol=1e-11
                ).x[:, -1]
            if backward:
                x.square().sum().backward()
        return x.detach()

    peer_f, peer_x = _timed(lambda: run("implicit_adams", False), repeats)
    peer_b, _ = _timed(lambda: run("implicit_adams", True), repeats)
    peer_err = float(np.max(np.abs(peer_x[0].numpy() - ref)))
    for kind in (("gauss_legendre", 2), ("radau_iia", 3)):
        ours_f, ours_x = _timed(lambda kind=kind: run(kind, False), repeats)
        ours_b, _ = _timed(lambda kind=kind: run(kind, True), repeats)
        for label, o, p in (("forward", ours_f, peer_f), ("forward+backward", ours_b, peer_b)):
            rows.append(
                {
                    "case": f"VdP mu=1 fixed dt={dt}, {kind[0]} s={kind[1]}, {label}",
                    "rtol": None,
                    "ours_error": float(np.max(np.abs(ours_x[0].numpy() - ref))),
                    "peer_error": peer_err,
                    "ours_s": o,
                    "peer": "torchdiffeq implicit_adams",
                    "peer_s": p,
                    "speedup": p / o,
                    "ours_steps": len(t) - 1,
                }
            )
    return rows


# ---------------------------------------------------------- section 3: IFT vs unrolled Newton
def _jacobian_in_graph(y, x):
    """``dy/dx`` (*batch, m, n) of a sample-wise map, kept in the autograd graph
    (``create_graph=True``) so that a backward pass differentiates through it too."""
    rows = []
    for i in range(y.shape[-1]):
        (row,) = torch.autograd.grad(y[..., i].sum(), x, create_graph=True, allow_unused=True)
        rows.append(torch.zeros_like(x) if row is None else row)
    return torch.stack(rows, dim=-2)


def unrolled_irk(f, x0, t, tab, tol=1e-12, max_iter=50):
    """Plain fixed-step IRK whose backward differentiates through every Newton iteration.

    Per step: stage equations ``K_i = f(t_k + c_i dt, x_k + dt sum_j a_ij K_j)`` (eq. 7.14, as
    ``R = K - f``), full Newton ``dR/dK dK = -R``, ``K <- K + dK`` (eq. 7.16-7.17) from
    ``K_i = f(t_k, x_k)`` until ``||dK||_inf <= tol (1 + ||K||_inf)``, then
    ``x_{k+1} = x_k + dt sum_i b_i K_i`` (eq. 7.18). Every operation, the Newton matrix
    ``dR/dK = I - dt (A kron I) blockdiag(df/dx(X_i))`` included, stays in the autograd graph,
    as in a naive PyTorch implementation (torchdiffeq's implicit solvers likewise keep their
    corrector iterations in the graph).

    Args:
        f: ``f(t, x) -> (*batch, n)``; x0: (*batch, n), requiring grad (the Newton matrix is
            formed by autograd w.r.t. the stage states); t: (T,) grid, one step per interval;
        tab: implicit ButcherTableau.

    Returns:
        ``(x_T, iterations)``: (*batch, n) final state and mean Newton iterations per step.
    """
    A, b, c, _ = tab.tensors(x0.dtype, x0.device)
    s, n = tab.stages, x0.shape[-1]
    batch = x0.shape[:-1]
    eye = torch.eye(s * n, dtype=x0.dtype, device=x0.device)
    x, iterations = x0, 0
    for k in range(t.shape[0] - 1):
        h = t[k + 1] - t[k]
        K = f(t[k], x).unsqueeze(-2).expand(*batch, s, n)
        for _ in range(max_iter):
            X = [x + h * (A[i] @ K) for i in range(s)]
            F = [f(t[k] + c[i] * h, X[i]) for i in range(s)]
            R = K - torch.stack(F, dim=-2)
            J = torch.stack([_jacobian_in_graph(F[i], X[i]) for i in range(s)], dim=-3)
            coupling = (A[:, :, None, None] * J[..., :, None, :, :]).transpose(-3, -2)
            M = eye - h * coupling.reshape(*batch, s * n, s * n)
            dK = -torch.linalg.solve(M, R.flatten(-2)).unflatten(-1, (s, n))
            K = K + dK
            iterations += 1
            if float(dK.detach().abs().max()) <= tol * (1 + float(K.detach().abs().max())):
                break
        x = x + h * (b @ K)
    return x, iterations / (t.shape[0] - 1)


def unrolled_newton(phi, x0, *args, tol=1e-12, max_iter=100):
    """Full Newton ``x <- x - J(x)^{-1} phi(x)`` (eq. 3.5-3.9) with autograd through every
    iteration (Jacobian by autograd, kept in the graph); stops when ``||phi||_inf <= tol``
    for the whole batch. ``x0`` must require grad. Returns ``(x, iterations)``."""
    x = x0
    for iteration in range(max_iter + 1):
        r = phi(x, *args)
        if float(r.detach().abs().max()) <= tol or iteration == max_iter:
            return x, iteration
        x = x - torch.linalg.solve(_jacobian_in_graph(r, x), r)


def _sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _forward_backward(forward, params, repeats, device):
    """Time ``forward`` + gradient (best of ``repeats``), then one more run measuring the
    graph's saved bytes and, on CUDA, the peak allocated memory above the start."""

    def once():
        loss, info = forward()
        grads = torch.autograd.grad(loss, params)
        _sync(device)
        return grads, info

    def measured():
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
            start = torch.cuda.memory_allocated(device)
        with GraphMemory() as meter:
            loss, info = forward()
            saved = meter.saved_bytes(loss)
        grads = torch.autograd.grad(loss, params)
        _sync(device)
        peak = None
        if device.type == "cuda":
            peak = (torch.cuda.max_memory_allocated(device) - start) / 2**20
        return {"saved_MB": saved / 2**20, "grads": grads, "info": info, "peak": peak}

    seconds, _ = _timed(once, repeats)
    return {"s": seconds, **with_large_stack(measured)}


def _grad_difference(ours, peer):
    """max over parameters of ``max|g_ours - g_peer| / max|g_peer|``."""
    return max(float((o - p).abs().max() / p.abs().max()) for o, p in zip(ours, peer, strict=True))


def _ift_row(case, ours, peer, fd_slope, ours_dir, peer_dir, errors, steps):
    row = {
        "case": case,
        "rtol": None,
        "ours_error": errors[0],
        "peer_error": errors[1],
        "ours_s": ours["s"],
        "peer": "unrolled autograd through Newton",
        "peer_s": peer["s"],
        "speedup": peer["s"] / ours["s"],
        "ours_steps": steps,
        "ours_newton_iters": ours["info"][0],
        "peer_newton_iters": peer["info"][0],
        "ours_saved_MB": ours["saved_MB"],
        "peer_saved_MB": peer["saved_MB"],
        "memory_ratio": peer["saved_MB"] / ours["saved_MB"],
        "grad_rel_diff": _grad_difference(ours["grads"], peer["grads"]),
        "ours_fd_error": abs(ours_dir - fd_slope) / abs(fd_slope),
        "peer_fd_error": abs(peer_dir - fd_slope) / abs(fd_slope),
    }
    if ours["peak"] is not None:
        row["ours_cuda_peak_MB"] = ours["peak"]
        row["peer_cuda_peak_MB"] = peer["peak"]
    return row


def ift_irk_rows(t_end, dt, batch, repeats, device, fd_step=1e-5):
    """Section 3a: fixed-step Gauss s=2 / Radau IIA s=3 on Van der Pol, IFT per step (ours)
    vs the same method with autograd through its Newton iterations (:func:`unrolled_irk`).

    Loss ``sum_batch |x(T)|^2``, gradients w.r.t. ``x0`` and the per-sample ``mu``; the
    finite difference is central in the direction ``mu + delta (1, ..., 1)``.
    """
    mus = np.linspace(0.5, 1.5, batch)
    x0_np = np.array([0.5, 1.0])
    ref = np.stack([_vdp_reference(mu, x0_np, t_end) for mu in mus])
    t = torch.linspace(0.0, t_end, int(round(t_end / dt)) + 1, device=device)
    model = _VdP(mus).to(device)
    x0 = torch.tensor(x0_np, device=device).expand(batch, 2).clone().requires_grad_(True)
    params = (x0, model.mu)
    options = dict(adaptive=False, rtol=1e-10, atol=1e-10)
    rows = []
    for tab in (gauss_legendre(2), radau_iia(3)):

        def ours_forward(tab=tab):
            sol = solve_implicit_ode(model, x0, t, tab, **options)
            iters = float(sol.stats.n_newton_iters.double().mean()) / (len(t) - 1)
            x = sol.x[:, -1]
            return x.square().sum(), (iters, x.detach().cpu().numpy())

        def peer_forward(tab=tab):
            x, iters = unrolled_irk(model, x0, t, tab)
            return x.square().sum(), (iters, x.detach().cpu().numpy())

        ours = _forward_backward(ours_forward, params, repeats, device)
        peer = _forward_backward(peer_forward, params, repeats, device)
        with torch.no_grad():
            mu0 = model.mu.detach().clone()
            losses = []
            for sign in (1.0, -1.0):
                model.mu.copy_(mu0 + sign * fd_step)
                x = solve_implicit_ode(model, x0.detach(), t, tab, **options).x[:, -1]
                losses.append(float(x.square().sum()))
            model.mu.copy_(mu0)
        fd_slope = (losses[0] - losses[1]) / (2 * fd_step)
        rows.append(
            _ift_row(
                f"VdP mu in [0.5, 1.5] x{batch}, dt={dt}, {tab.name}, IFT vs unrolled, fwd+bwd",
                ours,
                peer,
                fd_slope,
                float(ours["grads"][1].sum()),
                float(peer["grads"][1].sum()),
                tuple(float(np.max(np.abs(r["info"][1] - ref))) for r in (ours, peer)),
                len(t) - 1,
            )
        )
    return rows


def _root_problem(n, batch, seed, device):
    """``phi(x; M, b) = exp(x) + M x - b`` (per sample; ``M`` (n, n) shared, ``b`` (batch, n)):
    a regular root near ``log b``; from a start ``x0 = L`` Newton first walks down about one
    unit per iteration (``exp`` dominates), so ``L`` sets the number of iterations."""
    gen = torch.Generator().manual_seed(seed)
    M = 0.1 / n**0.5 * torch.randn(n, n, generator=gen, dtype=torch.float64)
    b = 1.0 + torch.rand(batch, n, generator=gen, dtype=torch.float64)
    M = M.to(device).requires_grad_(True)
    b = b.to(device).requires_grad_(True)

    def phi(x, M, b):
        return torch.exp(x) + x @ M.mT - b

    return phi, M, b


def ift_newton_rows(starts, n, batch, repeats, device, seed=0, tol=1e-12, fd_step=1e-6):
    """Section 3b: ``integrators.newton`` (full Newton, IFT gradient) vs :func:`unrolled_newton`
    on :func:`_root_problem` from starts ``x0 = L`` (more iterations for larger ``L``).

    Loss ``sum |x*|^2``, gradients w.r.t. ``M`` and ``b``; the finite difference is central in
    the direction ``b + delta (1, ..., 1)``; errors are ``max ||phi(x)||_inf``.
    """
    phi, M, b = _root_problem(n, batch, seed, device)
    rows = []
    for start in starts:
        x0 = torch.full((batch, n), float(start), dtype=torch.float64, device=device)

        def ours_forward(x0=x0):
            res = newton(phi, x0, M, b, tol=tol, max_iter=200)
            return res.x.square().sum(), (int(res.iterations.max()), res.x.detach())

        def peer_forward(x0=x0):
            x, iters = unrolled_newton(phi, x0.clone().requires_grad_(True), M, b, tol=tol)
            return x.square().sum(), (iters, x.detach())

        ours = _forward_backward(ours_forward, (M, b), repeats, device)
        peer = _forward_backward(peer_forward, (M, b), repeats, device)
        with torch.no_grad():
            errors = tuple(float(phi(r["info"][1], M, b).abs().max()) for r in (ours, peer))
            losses = [
                float(
                    newton(phi, x0, M, b + sign * fd_step, tol=tol, max_iter=200).x.square().sum()
                )
                for sign in (1.0, -1.0)
            ]
        fd_slope = (losses[0] - losses[1]) / (2 * fd_step)
        rows.append(
            _ift_row(
                f"newton exp(x)+Mx=b, n={n}, batch {batch}, x0={start}, IFT vs unrolled, fwd+bwd",
                ours,
                peer,
                fd_slope,
                float(ours["grads"][1].sum()),
                float(peer["grads"][1].sum()),
                errors,
                None,
            )
        )
    return rows


def _time_figure(rows, path):
    fig, ax = plt.subplots(figsize=(9, 0.3 * len(rows) + 1.5))
    y = np.arange(len(rows))
    # points, not bars: a bar's length means nothing on a log axis
    ax.semilogx([r["ours_s"] for r in rows], y, "o", label="ours")
    ax.semilogx([r["peer_s"] for r in rows], y, "s", mfc="none", label="peer")
    ax.set_yticks(y, [f"{r['case']} rtol={r['rtol']}" for r in rows], fontsize=6)
    ax.set_ylim(len(rows) - 0.5, -0.5)  # first case on top
    ax.grid(axis="y", color="0.9")
    ax.set_xlabel("wall time [s]")
    readable_log_ticks(ax.xaxis)
    ax.set_ylabel("case")
    ax.legend()
    fig.tight_layout()
    save_figure(fig, path)


def _memory_figure(newton_rows, path):
    """Saved-for-backward memory against Newton iterations (section 3b)."""
    fig, ax = plt.subplots(figsize=(5, 3.5))
    iters = [r["ours_newton_iters"] for r in newton_rows]
    ax.plot(iters, [r["ours_saved_MB"] for r in newton_rows], "o-", label="IFT (ours)")
    ax.plot(iters, [r["peer_saved_MB"] for r in newton_rows], "s-", label="unrolled autograd")
    ax.set_xlabel("Newton iterations")
    ax.set_ylabel("saved for backward [MB]")
    ax.set_ylim(bottom=0)
    ax.legend()
    fig.tight_layout()
    save_figure(fig, path)


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    device = torch.device(args.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    previous_dtype = torch.get_default_dtype()
    previous_threads = torch.get_num_threads()
    torch.set_default_dtype(torch.float64)
    torch.set_num_threads(args.threads)
    rows, newton_rows = [], []
    try:
        if args.quick:
            if 1 in args.sections:
                note(SECTIONS[1])
                rows += stiff_rows(
                    t_end=0.3, rtols=(1e-4,), batch=8, n_check=3, ref_rtol=1e-10, repeats=1
                )
            if 2 in args.sections:
                note(SECTIONS[2])
                rows += fixed_rows(t_end=1.0, dt=0.05, repeats=1)
            if 3 in args.sections:
                note(SECTIONS[3])
                rows += ift_irk_rows(t_end=1.0, dt=0.05, batch=4, repeats=1, device=device)
                newton_rows = ift_newton_rows((0, 10), n=8, batch=16, repeats=2, device=device)
        else:
            if 1 in args.sections:
                note(SECTIONS[1])
                rows += stiff_rows(
                    t_end=2.0,
                    rtols=(1e-6, 1e-9),
                    batch=args.batch,
                    n_check=8,
                    ref_rtol=1e-12,
                    repeats=args.repeats,
                    batch_rtols=args.batch_rtols,
                )
            if 2 in args.sections:
                note(SECTIONS[2])
                rows += fixed_rows(t_end=10.0, dt=0.01, repeats=args.repeats)
            if 3 in args.sections:
                note(SECTIONS[3])
                rows += ift_irk_rows(
                    t_end=10.0, dt=0.01, batch=16, repeats=args.repeats, device=device
                )
                newton_rows = ift_newton_rows(
                    (0, 5, 10, 20, 40), n=8, batch=256, repeats=args.repeats, device=device
                )
        rows += newton_rows
        markdown = write_table(rows, out / NAME)
        _time_figure(rows, out / f"{NAME}.png")
        if newton_rows:
            _memory_figure(newton_rows, out / f"{NAME}_ift_memory.png")
        finish(out, markdown)
        return rows
    finally:
        torch.set_default_dtype(previous_dtype)
        torch.set_num_threads(previous_threads)


if __name__ == "__main__":
    main()
