"""Fast, differentiable, batched IIR filtering ``y = (B(q) / A(q)) x`` with a monic ``A``.

Conventions (``q^-1`` is the backward shift, ``q^-1 x_k = x_{k-1}``):

- ``b``: ``(*batch, m)`` numerator coefficients ``b_0 .. b_{m-1}`` of
  ``B(q) = b_0 + b_1 q^-1 + ... + b_{m-1} q^{-(m-1)}`` (as ``scipy.signal.lfilter``'s ``b``);
- ``a``: ``(*batch, n)`` the coefficients ``a_1 .. a_n`` of the monic denominator
  ``A(q) = 1 + a_1 q^-1 + ... + a_n q^-n`` -- the leading 1 is NOT passed (scipy's ``a`` is
  ``[1, a_1, ..., a_n]``);
- ``x``: ``(*batch, N)``, filtered along the last dimension;
- ``zi``: ``(*batch, k)`` initial state in scipy's transposed direct form II convention
  (``k = max(n, m - 1)`` entries, as there). Its effect is exactly that of adding ``zi`` to
  the first ``k`` samples of ``B(q) x`` before the all-pole part ``1/A(q)``.

All batch shapes broadcast. Everything is pure torch, so it runs on any device.

Method. ``y = (1/A) (B x + zi)``, computed by blocks of length ``L`` (64 by default, smaller
for large batches of filters): inside a block the response to the block's input is a product
with the ``L x L`` lower-triangular Toeplitz matrix of the impulse response ``h`` of ``1/A``
(the FIR part ``B`` folded in: each block also sees its ``m - 1`` preceding inputs), and the
response to the block's initial state (the last ``n`` outputs of the previous block) is an
``L x n`` matrix times that state. The ``n``-dimensional block states obey a linear
recurrence ``s_{j+1} = M s_j + c_j`` that is solved by a prefix scan with doubling
(``log2(N/L)`` batched matmuls). ``O(N L)`` matmul-friendly work, no Python loop over samples
or blocks; ``h`` is one triangular solve with the banded Toeplitz matrix of ``A``. Where a
bound of the doubling's rounding errors is not small (poles clustered near the unit circle)
steps of iterative refinement follow, and where it is large the plain recursion replaces the
block method (see :func:`_allpole_apply`).

Gradients (adjoint method, one custom autograd node :class:`_IIR`; ``T`` is the
lower-triangular Toeplitz operator of ``1/A`` and ``g`` the upstream gradient):
``gw = T' g`` is the same all-pole filter run on the time-reversed ``g`` (reusing the forward
pass's block matrices); then ``dL/dx_k = sum_j b_j gw_{k+j}``, ``dL/db_j = sum_k gw_k x_{k-j}``,
``dL/da_i = -sum_k gw_k y_{k-i}`` (because ``dy/da_i = -(1/A) q^-i y``) and
``dL/dzi = gw[:k]``. Under ``create_graph=True`` the backward pass runs through the
differentiable :func:`allpole`, so higher derivatives work; a forward-mode rule (``jvp``) and
an automatic vmap rule serve ``torch.func.jacfwd`` / ``jacrev``.

CPU dispatch. For one filter shared by all signals (1-D ``b`` and ``a``) on CPU tensors, the
block method's fixed cost (building the Toeplitz blocks, the scan, ~15 small kernels) exceeds
the cost of the plain recursion in compiled code, so by default :func:`iir_filter` then runs
the two filtering passes (forward ``B/A`` and the adjoint ``1/A`` in backward) with
``scipy.signal.lfilter`` inside the same autograd node; the gradient formulas above are
unchanged and stay in torch. The pure-torch block path still serves CUDA, batched
coefficients, ``torch.func`` transforms and every higher derivative (the backward pass under
``create_graph=True`` is always the differentiable torch path). :func:`cpu_backend` selects
the path (``"auto"`` default, ``"torch"`` to force the block method, e.g. to benchmark it).
"""

from __future__ import annotations

import contextlib
import functools
import math

import numpy as np
import scipy.signal
import torch
import torch.nn.functional as F

from integrators.errors import InputValidationError

__all__ = ["allpole", "cpu_backend", "fir_filter", "iir_filter", "poly_mul"]

# The Toeplitz blocks of a batch of denominators use at most this many entries in all.
_TOEPLITZ_BUDGET = 1 << 22
_MAX_BLOCK = 64
#: bounds of the rounding errors of the doubling scan (relative to the block states, see
#: :func:`_allpole_plan`): used as it is up to the first, refined up to the second, above it
#: the plain recursion
_EXACT_DOUBLING, _REFINED_DOUBLING = 1e-12, 1e-4
#: steps of iterative refinement after a doubling scan with a moderate error bound
_REFINEMENTS = 2
_BACKENDS = ("auto", "torch")
_cpu_backend = "auto"


@contextlib.contextmanager
def cpu_backend(name: str):
    """Context manager choosing how :func:`iir_filter` filters CPU tensors.

    ``"auto"`` (the default): ``scipy.signal.lfilter`` for a single filter (1-D ``b`` and
    ``a``) on float32/float64 CPU tensors outside ``torch.func`` transforms, the pure-torch
    block method otherwise; ``"torch"``: always the block method.
    """
    global _cpu_backend
    if name not in _BACKENDS:
        raise InputValidationError(f"cpu_backend must be one of {_BACKENDS}, got {name!r}.")
    previous, _cpu_backend = _cpu_backend, name
    try:
        yield
    finally:
        _cpu_backend = previous


def _broadcast(*shapes) -> torch.Size:
    """Broadcast batch shapes (as ``torch.broadcast_shapes``, whose general Python
    implementation is slow for a per-call helper; this is a plain loop over the few
    dimensions)."""
    if all(shape == shapes[0] for shape in shapes[1:]):
        return torch.Size(shapes[0])
    ndim = max(len(shape) for shape in shapes)
    out = []
    padded = [(1,) * (ndim - len(shape)) + tuple(shape) for shape in shapes]
    for sizes in zip(*padded, strict=True):
        distinct = {size for size in sizes if size != 1}
        if len(distinct) > 1:
            raise InputValidationError(f"batch shapes {padded} do not broadcast.")
        out.append(distinct.pop() if distinct else 1)
    return torch.Size(out)


def _batch_numel(shape) -> int:
    return int(math.prod(shape))


def fir_filter(c: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Causal FIR filter ``y_k = sum_j c_j x_{k-j}`` with zero past, along the last dim.

    Computed as ``m`` shifted multiply-adds over whole signals (a loop over the taps, never
    over samples; exact, no FFT rounding, memory of one output).

    Args:
        c: ``(*batch_c, m)`` taps ``c_0 .. c_{m-1}``.
        x: ``(*batch_x, N)``.

    Returns:
        ``(*broadcast(batch_c, batch_x), N)``.
    """
    m, N = c.shape[-1], x.shape[-1]
    batch = _broadcast(c.shape[:-1], x.shape[:-1])
    if m == 0 or N == 0:
        return x.new_zeros(*batch, N)
    out = c[..., :1] * x  # a new (*batch, N) tensor, safe to update in place
    for j in range(1, min(m, N)):  # loop over the taps
        out[..., j:] += c[..., j : j + 1] * x[..., : N - j]
    return out


def poly_mul(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Product of polynomials given by coefficient tensors along the last dim (batched).

    ``(*b1, m) x (*b2, n) -> (*broadcast, m + n - 1)`` (``p`` or ``q`` empty -> empty).
    """
    m, n = p.shape[-1], q.shape[-1]
    batch = _broadcast(p.shape[:-1], q.shape[:-1])
    if m == 0 or n == 0:
        return p.new_zeros(*batch, 0)
    if m == 1 or n == 1:  # a constant factor (e.g. A = 1 in an OE model)
        return p * q
    outer = p.unsqueeze(-1) * q.unsqueeze(-2)  # (*batch, m, n)
    index = (
        torch.arange(m, device=p.device).unsqueeze(-1) + torch.arange(n, device=p.device)
    ).reshape(-1)
    out = p.new_zeros(*batch, m + n - 1)
    return out.index_add(-1, index, outer.reshape(*batch, m * n))


@functools.lru_cache(maxsize=64)
def _band_indices(L: int, n: int, device: torch.device):
    """Gather indices into ``[1, a_1, .., a_n, 0, .., 0]`` (length ``L + 1``; slot ``L`` is 0).

    ``A``: the ``L x L`` banded lower-triangular Toeplitz matrix of ``A(q)``;
    ``T``: the lower-triangular Toeplitz matrix of a sequence ``h`` padded with one zero;
    ``V``: ``V[t, m-1] = -a_{t+m}`` (t + m <= n): past outputs ``(y_-1, .., y_-n)`` act on
    ``1/A`` like the input ``V s`` from rest (``v_t = -sum_{i>t} a_i y_{t-i}``, t < n).
    """
    lag = torch.arange(L, device=device)
    lag = lag.unsqueeze(-1) - lag  # t - s
    band = torch.where((lag >= 0) & (lag <= n), lag, L).reshape(-1)
    lower = torch.where(lag >= 0, lag, L).reshape(-1)
    tm = torch.arange(n, device=device).unsqueeze(-1) + torch.arange(1, n + 1, device=device)
    past = torch.where(tm <= n, tm, L).reshape(-1)
    return band, lower, past


@functools.lru_cache(maxsize=64)
def _fir_band_index(L: int, m: int, device: torch.device) -> torch.Tensor:
    """Gather index into ``[b_0, .., b_{m-1}, 0]`` for the ``(L+m-1) x L`` matrix ``G`` with
    ``G[i, t] = b_{t+m-1-i}``: a block's FIR output is ``w = x_ext @ G``, where ``x_ext`` is the
    block with its ``m - 1`` preceding samples."""
    d = torch.arange(L, device=device) + (m - 1) - torch.arange(L + m - 1, device=device)[:, None]
    return torch.where((d >= 0) & (d <= m - 1), d, m).reshape(-1)


def _block_length(n: int, N: int, n_filters: int) -> int:
    """Samples per block: at most :data:`_MAX_BLOCK`, fewer for large batches of filters,
    and more than ``n`` (slot ``L`` of the padded coefficients must be a zero, see
    :func:`_band_indices`)."""
    L = int(math.sqrt(_TOEPLITZ_BUDGET / max(n_filters, 1)))
    return max(n + 1, min(N, _MAX_BLOCK, max(L, 16)))


def _block_matrices(a: torch.Tensor, L: int):
    """``T`` (``(*ba, L, L)``, the Toeplitz matrix of the impulse response of ``1/A``), ``Q``
    (``(*ba, L, n)``, the response to a block's initial state), the block transition ``M``
    (``(*ba, n, n)``) and a bound of the rounding error of ``M``'s entries (``(*ba,)``)."""
    n = a.shape[-1]
    band, lower, past = _band_indices(L, n, a.device)
    coeffs = F.pad(F.pad(a, (1, 0), value=1.0), (0, L - n))  # [1, a, 0...], length L + 1
    A = coeffs[..., band].reshape(*a.shape[:-1], L, L)
    e1 = F.pad(torch.ones_like(a[..., :1]), (0, L - 1)).unsqueeze(-1)
    h = torch.linalg.solve_triangular(A, e1, upper=False, unitriangular=True)  # impulse resp.
    T = F.pad(h[..., 0], (0, 1))[..., lower].reshape(*a.shape[:-1], L, L)
    V = -coeffs[..., past].reshape(*a.shape[:-1], n, n)
    Q = T[..., :, :n] @ V  # (*ba, L, n): response to the past outputs
    # block states s_j = (y_{jL-1}, ..., y_{jL-n}) obey s_{j+1} = M s_j + c_j
    M = Q[..., L - n :, :].flip(-2)
    eps = torch.finfo(a.dtype).eps
    error = n * eps * (T[..., L - n :, :n].abs() @ V.abs()).amax((-2, -1))
    return T, Q, M, error


def _allpole_plan(a: torch.Tensor, N: int):
    """What :func:`_allpole_apply` needs for ``1/A`` on ``N`` samples (depends on ``a`` only).

    Returns ``Tt`` (``(*ba, L, L)``, the transposed Toeplitz matrix of the impulse response),
    ``Qt`` (``(*ba, n, L)``, transposed response to a block's initial state), ``Mt``
    (``(K, *ba, n, n)``, transposed state-transition powers ``M^(2^k)`` for the scan by
    doubling) and ``refinements`` (0-dim: steps of iterative refinement after the block
    method). Where the doubling's rounding errors may be large (the first-order bound
    ``e_{k+1} = 2 |P_k| e_k + n eps |P_k|^2`` of the errors of the powers ``P_k``, from the
    error of ``M``, exceeds :data:`_REFINED_DOUBLING`), or cannot be read (``a`` under a
    ``torch.func`` transform), ``Tt``, ``Qt`` and ``Mt`` are empty: the plain recursion.
    """
    n = a.shape[-1]
    L = _block_length(n, N, _batch_numel(a.shape[:-1]))
    n_blocks = -(-N // L)
    T, Q, M, error = _block_matrices(a, L)
    powers, total = [M.transpose(-1, -2)], error
    while 2 ** len(powers) < n_blocks - 1:
        norm = powers[-1].abs().sum(-1).amax(-1)
        error = 2 * norm * error + n * a.new_tensor(torch.finfo(a.dtype).eps) * norm**2
        total = total + error
        powers.append(powers[-1] @ powers[-1])
    bound = math.inf
    if not torch._C._functorch.is_functorch_wrapped_tensor(a):
        bound = float(total.nan_to_num(math.inf).max()) if total.numel() else 0.0
    if bound > _REFINED_DOUBLING:
        empty = a.new_zeros(0, 0)
        return empty, empty, a.new_zeros(0, 0, 0), torch.zeros((), dtype=torch.int64)
    refinements = 0 if bound <= _EXACT_DOUBLING else _REFINEMENTS
    steps = torch.tensor(refinements, dtype=torch.int64)
    return T.transpose(-1, -2), Q.transpose(-1, -2), torch.stack(powers), steps


def _allpole_apply(a: torch.Tensor, plan, w: torch.Tensor, b: torch.Tensor | None = None):
    """``y = (1/A) w`` from rest with what :func:`_allpole_plan` chose.

    With ``b``: ``y = (B/A) w``, the FIR part folded into the block matmul (each block sees its
    ``m - 1`` preceding samples), which saves ``m`` passes over the signal.

    Accuracy. Where poles cluster near the unit circle the block transition ``M`` has large
    entries in the basis of past outputs, and squaring it for the doubling scan moves the
    eigenvalues of its powers outside the unit circle (``(1 - 0.99 q^-1)^4``: outputs wrong
    by a factor 6; ``(1 - 0.95 q^-1)^6``: by 1e26). A moderate bound of these errors is
    removed by steps of iterative refinement (solving again for the residual ``B w - A y``,
    computed by the recursion's own FIR form); beyond it the plan is the plain recursion,
    one sample after the other, as accurate as ``scipy.signal.lfilter``.
    """
    if plan[0].numel() == 0:
        return _recursion(a, w if b is None else fir_filter(b, w))
    y = _block_solve(plan, w, b)
    if int(plan[3]) == 0:
        return y
    target = w if b is None else fir_filter(b, w)
    monic = F.pad(a, (1, 0), value=1.0)
    for _ in range(int(plan[3])):
        y = y + _block_solve(plan, target - fir_filter(monic, y))
    return y


def _recursion(a: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """``y_k = w_k - sum_i a_i y_{k-i}`` from rest, one sample after the other (a loop over
    the samples, vectorised over the batch): the fallback of :func:`_allpole_apply`."""
    n, N = a.shape[-1], w.shape[-1]
    batch = _broadcast(a.shape[:-1], w.shape[:-1])
    # a zero of a's batch makes y batched like a also under vmap (in-place updates below)
    y = (w + torch.zeros_like(a[..., :1])).expand(*batch, N).clone()
    reversed_a = a.flip(-1)  # a_n .. a_1
    for k in range(1, N):
        lo = max(0, k - n)
        y[..., k] -= (y[..., lo:k] * reversed_a[..., n - (k - lo) :]).sum(-1)
    return y


def _block_solve(plan, w: torch.Tensor, b: torch.Tensor | None = None) -> torch.Tensor:
    """One block-method evaluation of ``(B/A) w`` (``(1/A) w`` without ``b``), see
    :func:`_allpole_apply`."""
    Tt, Qt, Mt, _ = plan
    n, L = Qt.shape[-2], Qt.shape[-1]
    N = w.shape[-1]
    n_blocks = -(-N // L)
    if b is None:
        batch = _broadcast(Tt.shape[:-2], w.shape[:-1])
        blocks = F.pad(w, (0, n_blocks * L - N)).expand(*batch, n_blocks * L)
        P = blocks.reshape(*batch, n_blocks, L) @ Tt  # (*batch, n_blocks, L) from rest
    else:
        m = b.shape[-1]
        batch = _broadcast(Tt.shape[:-2], b.shape[:-1], w.shape[:-1])
        G = F.pad(b, (0, 1))[..., _fir_band_index(L, m, b.device)]
        K = G.reshape(*b.shape[:-1], L + m - 1, L) @ Tt  # (*, L + m - 1, L)
        ext = F.pad(w, (m - 1, n_blocks * L - N)).unfold(-1, L + m - 1, L)
        P = (ext @ K).expand(*batch, n_blocks, L).contiguous()
    # inclusive prefix scan by doubling: r_j = sum_{i<=j} M^(j-i) c_i = s_{j+1}
    r = P[..., L - n :].flip(-1)  # c_j, a new tensor
    for k in range(Mt.shape[0]):  # log2(n_blocks) steps
        d = 2**k
        if d >= n_blocks - 1:
            break
        r[..., d:, :] += r[..., :-d, :] @ Mt[k]
    S = F.pad(r[..., :-1, :], (0, 0, 1, 0))  # (*batch, n_blocks, n), s_0 = 0
    P += S @ Qt  # add each block's response to its initial state
    return P.reshape(*batch, n_blocks * L)[..., :N]


def _allpole_forward(a: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Exact block evaluation of ``y = (1/A) w`` from rest (see the module docstring)."""
    n, N = a.shape[-1], w.shape[-1]
    if n == 0 or N == 0:
        return w.clone()
    return _allpole_apply(a, _allpole_plan(a, N), w)


def _lagged_dots(g: torch.Tensor, x: torch.Tensor, lags) -> torch.Tensor:
    """``r_j = sum_k g_k x_{k-j}`` for each lag j (``(*batch, len(lags))``), as dot products.

    A single signal (batch of one element) takes ``torch.dot`` on 1-D views (the BLAS dot,
    faster than a ``(1, N) @ (N, 1)`` matmul; see docs/benchmarks.md, ``bench_filter``)."""
    N = x.shape[-1]
    batch = _broadcast(g.shape[:-1], x.shape[:-1])
    if batch.numel() == 1 and g.shape[:-1].numel() == 1 and x.shape[:-1].numel() == 1:
        g1, x1 = g.reshape(N), x.reshape(N)
        dots = [torch.dot(g1[j:], x1[: N - j]) if j < N else g1.new_zeros(()) for j in lags]
        return (torch.stack(dots) if dots else g.new_zeros(0)).reshape(*batch, -1)
    out = []
    for j in lags:  # loop over the filter order
        if j >= N:
            out.append(g.new_zeros(batch))
        else:
            dot = g[..., j:].unsqueeze(-2) @ x[..., : N - j].unsqueeze(-1)
            out.append(dot[..., 0, 0].expand(batch))
    return torch.stack(out, dim=-1) if out else g.new_zeros(*batch, 0)


def _fir_adjoint(c: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Adjoint of :func:`fir_filter` in x: ``r_k = sum_j c_j g_{k+j}``."""
    m, N = c.shape[-1], g.shape[-1]
    out = c[..., :1] * g
    for j in range(1, min(m, N)):  # loop over the taps
        out[..., : N - j] += c[..., j : j + 1] * g[..., j:]
    return out


def _lagged_filter(da: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """``sum_i da_i y_{k-i}`` (i = 1..n) for every k: an FIR filter with a zero first tap."""
    return fir_filter(F.pad(da, (1, 0)), y)


class _AllPole(torch.autograd.Function):
    """``y = (1/A) w`` from rest, with adjoint backward and forward-mode rules."""

    generate_vmap_rule = True

    @staticmethod
    def forward(a, w):
        return _allpole_forward(a, w)

    @staticmethod
    def setup_context(ctx, inputs, output):
        a, w = inputs
        ctx.save_for_backward(a, output)
        ctx.save_for_forward(a, output)
        ctx.w_shape = w.shape
        ctx.set_materialize_grads(True)

    @staticmethod
    def backward(ctx, grad_y):
        a, y = ctx.saved_tensors
        grad_a = grad_w = None
        # adjoint: the same filter on the time-reversed upstream gradient
        gw = _AllPole.apply(a, grad_y.flip(-1)).flip(-1)
        if ctx.needs_input_grad[1]:
            grad_w = gw.sum_to_size(ctx.w_shape)
        if ctx.needs_input_grad[0]:
            grad_a = (-_lagged_dots(gw, y, range(1, a.shape[-1] + 1))).sum_to_size(a.shape)
        return grad_a, grad_w

    @staticmethod
    def jvp(ctx, da, dw):
        a, y = ctx.saved_tensors
        rhs = torch.zeros_like(y) if dw is None else dw.expand_as(y)
        if da is not None:
            rhs = rhs - _lagged_filter(da, y)
        return _AllPole.apply(a, rhs)


def allpole(a: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """All-pole filter ``y = w / A(q)`` from rest: ``y_k = w_k - sum_i a_i y_{k-i}``.

    Args:
        a: ``(*batch_a, n)`` coefficients ``a_1 .. a_n`` of the monic ``A`` (no leading 1).
        w: ``(*batch_w, N)``.

    Returns:
        ``(*broadcast, N)``; differentiable in ``a`` and ``w`` (custom adjoint backward).
    """
    if a.shape[-1] == 0:
        return w.expand(*_broadcast(a.shape[:-1], w.shape[:-1]), w.shape[-1])
    return _AllPole.apply(a, w)


def _add_initial_state(w: torch.Tensor, zi: torch.Tensor) -> torch.Tensor:
    """``w`` with ``zi`` added to its first samples (``zi`` longer than ``w`` is cut)."""
    N = w.shape[-1]
    k = min(zi.shape[-1], N)
    if k == 0:
        return w
    batch = _broadcast(w.shape[:-1], zi.shape[:-1])
    return w.expand(*batch, N) + F.pad(zi[..., :k], (0, N - k))


def _scipy_eligible(b, a, x, zi) -> bool:
    """True where :func:`iir_filter` may use ``scipy.signal.lfilter`` (see the module doc)."""
    if _cpu_backend != "auto" or b.shape[:-1].numel() != 1 or a.shape[:-1].numel() != 1:
        return False
    if x.device.type != "cpu" or x.dtype not in (torch.float32, torch.float64):
        return False
    n, m, N = a.shape[-1], b.shape[-1], x.shape[-1]
    if n == 0 or m == 0 or N == 0:
        return False
    batch = _broadcast(b.shape[:-1], a.shape[:-1], x.shape[:-1])
    if batch.numel() != x.shape[:-1].numel():
        return False
    if zi.shape[-1] != 0 and tuple(zi.shape) != (*x.shape[:-1], max(n, m - 1)):
        return False
    wrapped = torch._C._functorch.is_functorch_wrapped_tensor
    return not any(wrapped(t) for t in (b, a, x, zi))


def _scipy_lfilter(b, a, x: torch.Tensor, zi=None, reverse: bool = False) -> torch.Tensor:
    """``(B/A) x`` along the last dimension by ``scipy.signal.lfilter`` (CPU; ``b`` and ``a``
    hold one filter, possibly with leading dimensions of size 1; the output has the broadcast
    batch shape). ``reverse=True`` filters the time-reversed ``x`` and reverses the result
    (the adjoint pass) without extra copies; ``b = None`` means ``B = 1``."""
    num = np.ones(1) if b is None else b.detach().double().reshape(-1).numpy()
    den = np.concatenate([[1.0], a.detach().double().reshape(-1).numpy()])
    xn = x.detach().numpy()
    if zi is None or zi.shape[-1] == 0:  # lfilter reads the reversed view in place
        y = scipy.signal.lfilter(num, den, xn[..., ::-1] if reverse else xn, axis=-1)
    else:
        y = scipy.signal.lfilter(num, den, xn, axis=-1, zi=zi.detach().numpy())[0]
    batch = x.shape[:-1] if b is None else _broadcast(b.shape[:-1], a.shape[:-1], x.shape[:-1])
    y = torch.from_numpy(np.ascontiguousarray(y).reshape(*batch, x.shape[-1])).to(x.dtype)
    return y.flip(-1) if reverse else y


def _empty_plan(like: torch.Tensor):
    empty = like.new_zeros(0, 0)
    return empty, empty, like.new_zeros(0, 0, 0), torch.zeros((), dtype=torch.int64)


class _IIR(torch.autograd.Function):
    """``y = (1/A) (B x + zi)`` in one node: adjoint backward without an autograd graph.

    Returns ``(y, *plan)``; the block-method matrices (``plan``, non-differentiable) are
    returned so that the backward pass reuses them for the adjoint filter.
    """

    generate_vmap_rule = True

    @staticmethod
    def forward(b, a, x, zi):
        if _scipy_eligible(b, a, x, zi):
            return _scipy_lfilter(b, a, x, zi), *_empty_plan(x)
        N = x.shape[-1]
        if a.shape[-1] == 0 or N == 0 or b.shape[-1] == 0:
            w = _add_initial_state(fir_filter(b, x), zi)
            return _allpole_forward(a, w), *_empty_plan(w)
        plan = _allpole_plan(a, N)
        if zi.shape[-1] == 0:
            return _allpole_apply(a, plan, x, b), *plan
        return _allpole_apply(a, plan, _add_initial_state(fir_filter(b, x), zi)), *plan

    @staticmethod
    def setup_context(ctx, inputs, output):
        b, a, x, zi = inputs
        y, *plan = output
        ctx.mark_non_differentiable(*plan)
        ctx.save_for_backward(b, a, x, y, *plan)
        ctx.save_for_forward(b, a, x, y)
        ctx.zi_shape = zi.shape
        ctx.scipy = _scipy_eligible(b, a, x, zi)  # forward's choice
        ctx.set_materialize_grads(True)

    @staticmethod
    def backward(ctx, grad_y, *_):
        b, a, x, y, *plan = ctx.saved_tensors
        need_b, need_a, need_x, need_zi = ctx.needs_input_grad
        # adjoint of 1/A: the same filter on the time-reversed upstream gradient
        if torch.is_grad_enabled() or a.shape[-1] == 0:  # double backward: differentiable path
            gw = allpole(a, grad_y.flip(-1)).flip(-1)
        elif ctx.scipy:
            gw = _scipy_lfilter(None, a, grad_y, reverse=True)
        else:
            gw = _allpole_apply(a, plan, grad_y.flip(-1)).flip(-1)
        grad_b = grad_a = grad_x = grad_zi = None
        if need_b:
            grad_b = _lagged_dots(gw, x, range(b.shape[-1])).sum_to_size(b.shape)
        if need_a:
            grad_a = (-_lagged_dots(gw, y, range(1, a.shape[-1] + 1))).sum_to_size(a.shape)
        if need_x:
            grad_x = _fir_adjoint(b, gw).sum_to_size(x.shape)
        if need_zi:
            k = min(ctx.zi_shape[-1], gw.shape[-1])
            grad_zi = F.pad(gw[..., :k], (0, ctx.zi_shape[-1] - k)).sum_to_size(ctx.zi_shape)
        return grad_b, grad_a, grad_x, grad_zi

    @staticmethod
    def jvp(ctx, db, da, dx, dzi):
        b, a, x, y = ctx.saved_tensors
        rhs = torch.zeros_like(y)
        if db is not None:
            rhs = rhs + fir_filter(db, x)
        if dx is not None:
            rhs = rhs + fir_filter(b, dx)
        if dzi is not None:
            rhs = _add_initial_state(rhs, dzi)
        if da is not None:
            rhs = rhs - _lagged_filter(da, y)
        return allpole(a, rhs), None, None, None, None


def iir_filter(
    b: torch.Tensor, a: torch.Tensor, x: torch.Tensor, zi: torch.Tensor | None = None
) -> torch.Tensor:
    """Filter ``x`` with ``B(q)/A(q)`` (monic ``A``) along the last dimension.

    Equals ``scipy.signal.lfilter(b, [1, *a], x, zi=zi)[0]`` for each batch member.

    Args:
        b: ``(*batch, m)`` numerator ``b_0 .. b_{m-1}``.
        a: ``(*batch, n)`` denominator tail ``a_1 .. a_n`` (``A = 1 + a_1 q^-1 + ...``).
        x: ``(*batch, N)`` signal.
        zi: optional ``(*batch, k)`` initial state (scipy's convention, ``k = max(n, m-1)``).

    Returns:
        ``(*batch, N)`` with the broadcast batch shape. Differentiable in ``b``, ``a``, ``x``
        and ``zi`` (one custom autograd node; forward mode and higher derivatives work).
    """
    for name, t in (("b", b), ("a", a), ("x", x)):
        if not isinstance(t, torch.Tensor) or t.ndim < 1:
            raise InputValidationError(f"{name} must be a tensor with at least one dimension.")
    if not (b.dtype == a.dtype == x.dtype) or not x.is_floating_point():
        raise InputValidationError(
            f"b, a and x must share one float dtype; got {b.dtype}, {a.dtype}, {x.dtype}."
        )
    if zi is None:
        zi = x.new_zeros(0)
    elif not isinstance(zi, torch.Tensor) or zi.ndim < 1:
        raise InputValidationError("zi must be a tensor (*batch, k) with k = max(n, m - 1).")
    elif zi.dtype != x.dtype:
        raise InputValidationError(f"zi has dtype {zi.dtype} but x has {x.dtype}.")
    elif zi.shape[-1] != (k := max(a.shape[-1], b.shape[-1] - 1)):
        raise InputValidationError(
            f"zi has {zi.shape[-1]} entries in its last dimension but this filter's state has "
            f"k = max(n, m - 1) = {k} (n = {a.shape[-1]} denominator coefficients a_1..a_n, "
            f"m = {b.shape[-1]} numerator coefficients): give zi of shape (*batch, {k}), "
            "e.g. from scipy.signal.lfilter_zi, or zi=None for a start at rest."
        )
    return _IIR.apply(b, a, x, zi)[0]
