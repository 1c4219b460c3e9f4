"""Collocation polynomials of implicit RK steps: stage extrapolation and dense output.

Inside a collocation step ``[t_k, t_k + h]`` the state is (notes eq. 7.44)
``x(t_k + theta h) = x_k + h sum_i w_i(theta) K_i`` with ``w_i(theta) = int_0^theta l_i``, and
the stage derivatives/algebraic stages are the values at ``c_i`` of the degree ``s - 1``
polynomials ``sum_j K_j l_j(tau)`` / ``sum_j Z_j l_j(tau)``. Extrapolating those polynomials
past ``tau = 1`` gives the starting guess of the next step's Newton iteration.
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from .collocation import collocation_output_weights, lagrange_basis
from .errors import TableauError


def extrapolation_matrix(
    c: np.ndarray, ratio, coefficients: np.ndarray | None = None
) -> np.ndarray:
    """Lagrange matrix of the next step's stage guess, computed on the host: the basis of
    :func:`~integrators.collocation.lagrange_basis` through its monomial coefficients, so a
    batch of step ratios costs one 2-D product (the nodes are few and well separated; the
    two agree to rounding).

    The previous step's stage polynomial ``sum_j W_j l_j(tau)`` evaluated at the next step's
    nodes ``tau_i = 1 + c_i ratio`` is ``L @ W`` with ``L[i, j] = l_j(1 + c_i ratio)``.

    Args:
        c: (s,) nodes; ratio: float or (*batch,) array ``h_new / h_old``.
        coefficients: :func:`lagrange_coefficients` of ``c`` where the caller keeps them.

    Returns:
        (*batch, s, s) ``L``.
    """
    s = c.shape[0]
    tau = 1.0 + c * np.asarray(ratio, dtype=np.float64)[..., None]  # (*batch, s)
    powers = tau.reshape(-1, 1) ** np.arange(s)  # (batch * s, s): one 2-D product
    if coefficients is None:
        coefficients = lagrange_coefficients(tuple(c))
    return (powers @ coefficients).reshape(*tau.shape, s)


@functools.lru_cache(maxsize=16)
def lagrange_coefficients(c: tuple) -> np.ndarray:
    """``C`` with ``l_j(tau) = sum_q C[q, j] tau^q``: the inverse of the Vandermonde matrix
    ``c_m^q`` of the nodes (``l_j(c_m) = delta_jm``)."""
    return np.linalg.inv(np.vander(np.array(c), len(c), increasing=True))


def is_collocation(tab) -> bool:
    """True when ``tab`` is a collocation method (then eq. 7.44 gives dense output)."""
    try:
        collocation_output_weights(tab, [0.5])
    except TableauError:
        return False
    return True


class StepRecords:
    """Per-step data of an integration, one record per driver iteration for every sample.

    A sample that did not advance in an iteration has start time ``+inf`` in that record;
    the other start times of a sample increase, so the last record starting at or before a
    query time is the step containing it. ``stop`` ((*batch,) host array or None) holds the
    time each sample stopped at, ``+inf`` for the ones that finished: states at later times
    are NaN (:func:`nan_beyond`).
    """

    def __init__(self, tab, n: int):
        self.tab, self.n = tab, n
        self.t0, self.h, self.x, self.W, self.z = [], [], [], [], []
        self.stop = None

    def append(self, t0, h, x, W, z):
        """Add a record: t0, h (*batch,) (tensors or host arrays), x (*batch, n),
        W (*batch, s, p), z (*batch, m)."""
        self.t0.append(t0)
        self.h.append(h)
        self.x.append(x)
        self.W.append(W)
        self.z.append(z)

    def evaluate(self, tq: torch.Tensor, interior: bool = False):
        """States at times ``tq`` (M,): ``(x (*batch, M, n), z (*batch, M, m))``; with
        ``interior`` also a (*batch, M) bool tensor marking the times strictly inside a step
        (where ``z`` is interpolated, not a stage value that solves the algebraic equations) and
        the derivative ``x'`` (*batch, M, n) of the stage polynomial there."""
        t0 = _stack(self.t0, tq)  # (L, *batch)
        batch = t0.shape[1:]
        L = t0.shape[0]
        t0f = t0.reshape(L, -1)
        B = t0f.shape[1]
        started = t0f[None, :, :] <= tq[:, None, None]  # (M, L, B)
        idx = (L - 1) - started.flip(1).to(torch.uint8).argmax(1)  # last record started
        idx = torch.where(started.any(1), idx, 0)  # (M, B)
        cols = torch.arange(B, device=tq.device)[None, :].expand_as(idx)

        def take(seq):
            stacked = torch.stack(seq).reshape(L, B, *seq[0].shape[len(batch) :])
            return stacked[idx, cols]  # (M, B, ...)

        h = _stack(self.h, tq).reshape(L, B)[idx, cols]
        start = t0f[idx, cols]
        theta = ((tq[:, None] - start) / h).clamp(0.0, 1.0)
        W = take(self.W)
        x0 = take(self.x)
        n = self.n
        w = collocation_output_weights(self.tab, theta)  # (M, B, s)
        x = x0 + h[..., None] * torch.einsum("mbs,mbsn->mbn", w, W[..., :n])
        z0 = take(self.z)
        c = torch.as_tensor(np.array(self.tab.c), dtype=x.dtype, device=x.device)
        if z0.shape[-1]:
            nodes = torch.cat([c.new_zeros(1), c])
            basis = lagrange_basis(nodes, theta)  # (M, B, s + 1)
            values = torch.cat([z0[..., None, :], W[..., n:]], dim=-2)
            z = torch.einsum("mbq,mbqk->mbk", basis, values)
        else:
            z = z0
        M = tq.shape[0]
        x = x.permute(1, 0, 2).reshape(*batch, M, n)
        z = z.permute(1, 0, 2).reshape(*batch, M, z.shape[-1])
        if self.stop is not None:
            x, z = nan_beyond(x, tq, self.stop), nan_beyond(z, tq, self.stop)
        if not interior:
            return x, z
        inside = ((theta > 0) & (theta < 1)).permute(1, 0).reshape(*batch, M)
        xdot = torch.einsum("mbs,mbsn->mbn", lagrange_basis(c, theta), W[..., :n])
        return x, z, inside, xdot.permute(1, 0, 2).reshape(*batch, M, n)


def stop_times(status: np.ndarray, reached) -> np.ndarray:
    """(*batch,) float64 host array: the time ``reached`` (host array or float) where
    ``status`` (host int codes) is not SUCCESS, ``+inf`` elsewhere."""
    return np.where(status != 0, np.asarray(reached, dtype=np.float64), np.inf)


def nan_beyond(values: torch.Tensor, tq: torch.Tensor, stop: np.ndarray) -> torch.Tensor:
    """``values`` (*batch, M, k) at times ``tq`` (M,) with NaN at the times after each sample's
    stop time (``stop`` (*batch,) or (1,) host array, ``+inf`` for a finished sample): the
    outputs of a failed sample end where its integration ended. A selection, so the gradient
    of the remaining outputs stays finite."""
    if values.shape[-1] == 0 or not np.isfinite(stop).any():
        return values
    stop_t = torch.as_tensor(stop, dtype=tq.dtype, device=tq.device).reshape(values.shape[:-2])
    beyond = tq > stop_t[..., None]  # (*batch, M)
    return torch.where(beyond[..., None], torch.full_like(values, float("nan")), values)


def _stack(seq, like: torch.Tensor) -> torch.Tensor:
    """Stack per-step (*batch,) times or steps, given as tensors or host arrays: (L, *batch)."""
    if isinstance(seq[0], np.ndarray):
        return torch.as_tensor(np.stack(seq), dtype=like.dtype, device=like.device)
    return torch.stack(seq)
