"""The numpy kernels of adaptive Radau IIA, for small CPU problems, and the kernel choice.

:class:`NumpyKernel` does the per-step work of :func:`integrators.radau.adaptive_loop` (notes
§7.4, simplified Newton eq. 7.14-7.16, step eq. 7.18; see :mod:`integrators.radau` for the
error estimate and the step-size rule) on host (numpy) arrays, so the steps, counters,
statuses and messages are those of the torch kernel. Only the user's model runs in torch (on
``torch.from_numpy`` views of the host arrays, all stages in one call when the model allows
it); its Jacobian comes from :meth:`IRKCore.frozen_blocks` (autograd). For a batch of a few
samples a numpy operation costs a fraction of a tiny torch kernel's dispatch. One float64
trajectory takes :class:`OneTrajectoryKernel`, the same work on one sample with which the loop
keeps its per-sample quantities as Python floats (:func:`one_trajectory`).

Gradients: the numpy kernel finds the accepted steps ``(t_k, h_k)`` and converged stages
``W_k`` without autograd; when anything requires grad, those steps are replayed in torch with the
implicit-function-theorem stages ``core.ift`` and ``x_{k+1} = x_k + h_k sum_i b_i K_i``
(eq. 7.18), exactly as the torch kernel builds them, so gradients are the same.

Only explicit ODEs whose Newton matrix is inverted explicitly (``s n <= 24``) take this path
(:func:`host_loop_supported`); everything else stays on the torch kernel.
"""

from __future__ import annotations

import contextlib
import functools
import math

import numpy as np
import torch
from scipy.linalg import get_lapack_funcs

from ._irk_core import IRKCore, StageInputs, host_shape, masked_update
from ._irk_dense import StepRecords, extrapolation_matrix, lagrange_coefficients
from ._per_sample import ArrayOps
from .errors import InputValidationError
from .radau import embedded_weights

# Largest ``x0.numel()`` that "auto" sends to the numpy kernels: below the measured crossover
# with the torch kernel, near 1500 (docs/benchmarks.md, "Tuning constants").
HOST_MAX_NUMEL = 1024


def host_loop_supported(core: IRKCore, x0: torch.Tensor, adaptive: bool = True) -> str | None:
    """None when the host loop can run this problem, else the reason it cannot."""
    if not adaptive:
        return "the host loop runs adaptive Radau IIA only, not fixed steps"
    if x0.dtype not in (torch.float32, torch.float64):
        return f"the state is {x0.dtype}, the host loop computes in float32 or float64"
    if x0.device.type != "cpu":
        return f"the state lives on {x0.device}, the host loop runs on the CPU only"
    if core.system.kind != "ode":
        return "implicit ODEs and DAEs use the torch driver"
    if not core.solver.dense(core.system.n):
        return (
            f"the Newton matrix has s n = {core.s * core.system.n} > 24 rows (or linear_solver "
            "is not 'auto'/'transformed'); only small systems take the host loop"
        )
    return None


def use_host_loop(core: IRKCore, x0: torch.Tensor, option, adaptive: bool = True) -> bool:
    """Decide the driver from the ``host_loop`` option ("auto", True or False) of an
    integration with (``adaptive``) or without step-size control.

    Raises:
        InputValidationError: ``host_loop=True`` for a problem the host loop cannot run, or an
            unknown option value.
    """
    if option is False:
        return False
    why = host_loop_supported(core, x0, adaptive)
    if option is True:
        if why is not None:
            raise InputValidationError(f"host_loop=True is not possible here: {why}.")
        return True
    if option != "auto":
        raise InputValidationError(f"host_loop must be 'auto', True or False, got {option!r}.")
    return why is None and x0.numel() <= HOST_MAX_NUMEL


class _HostModel:
    """The user's ``f`` on host arrays. Host arrays carry the flattened batch ``B`` as one
    axis; the model sees zero-copy tensor views with the caller's batch shape, and its
    outputs come back as numpy arrays of the state dtype."""

    def __init__(self, core: IRKCore, batch, npdt):
        self.core, self.batch, self.npdt = core, tuple(batch), npdt
        self.B = int(np.prod(batch)) if len(batch) else 1
        self._inputs_at = self._inputs = None  # stage times and the inputs there

    def times(self, tt: np.ndarray) -> torch.Tensor:
        """Host times (*lead, B) as a tensor (*lead, *batch, 1)."""
        return torch.from_numpy(_writable(tt).reshape(*tt.shape[:-1], *self.batch, 1))

    def state(self, x: np.ndarray) -> torch.Tensor:
        """Host states (*lead, B, k) as a tensor (*lead, *batch, k)."""
        return torch.from_numpy(_writable(x).reshape(*x.shape[:-2], *self.batch, x.shape[-1]))

    def back(self, y: torch.Tensor, like: np.ndarray) -> np.ndarray:
        """A model output (*lead, *batch, k) as a host array shaped like ``like``
        (*lead, B, k)."""
        out = (y.detach() if y.requires_grad else y).numpy()
        if out.dtype != self.npdt:
            out = out.astype(self.npdt)
        if out.size != like.size:  # an output that broadcasts against the batch
            out = np.broadcast_to(out, (*like.shape[:-2], *self.batch, like.shape[-1]))
        return out.reshape(like.shape)

    def f(self, tt: np.ndarray, x: np.ndarray, z: torch.Tensor) -> np.ndarray:
        """``f(t, x)`` at host times (B,) and states (B, n); counts one call. Runs under the
        caller's ``torch.no_grad`` (a model may still call autograd inside)."""
        self.core.n_f_evals += 1
        t_t = self.times(tt)
        y = self.core.system.rhs_f(t_t, self.state(x), z, self.core.signal.at(t_t))
        return self.back(y, x)

    def stages(self, t_stage: torch.Tensor, X: np.ndarray, z: torch.Tensor) -> np.ndarray:
        """``f`` at the stage times ``t_stage`` (s, *batch, 1) (:meth:`times`) and stage states
        (s, B, n) (a strided view is fine): one stacked call when ``core.stack_stages``, else
        one call per stage; counts ``s`` calls. Runs under the caller's ``torch.no_grad``."""
        core = self.core
        core.n_f_evals += core.s
        inputs = self._stage_inputs(t_stage)
        if core.stack_stages:
            return self.back(core.system.rhs_f(t_stage, self.state(X), None, inputs.stacked), X)
        out = np.empty(X.shape, dtype=self.npdt)
        for i in range(core.s):
            y = core.system.rhs_f(t_stage[i], self.state(X[i]), z, inputs[i])
            out[i] = self.back(y, X[i])
        return out

    def _stage_inputs(self, t_stage: torch.Tensor) -> StageInputs:
        """The inputs at the stage times ``t_stage`` (s, *batch, 1), looked up once per step:
        kept while the Newton iterations pass the same stage-time tensor. A zero-order hold
        holds the input at the first stage time, in the step's sample interval (the steps end
        at the sample times), like :meth:`IRKCore.stage_inputs` from the step start."""
        if self._inputs_at is not t_stage:
            signal, held = self.core.signal, t_stage[0]
            self._inputs_at = t_stage
            self._inputs = StageInputs([signal.at(t_i, held) for t_i in t_stage], len(self.batch))
        return self._inputs

    def decide_stacking(self, tk, h, t_stage, K, X) -> None:
        """Set ``core.stack_stages`` once, by the torch driver's own test
        (:meth:`IRKCore.stacking_works`) at the first stage values ``K, X`` (B, s, n);
        ``tk, h`` (B,), ``t_stage`` (s, *batch, 1) tensor."""
        core, batch = self.core, self.batch
        tk_t, h_t = self.times(tk), torch.from_numpy(h).reshape(batch)
        times = core.stage_times(tk_t, h_t[..., None], len(batch), stacked=t_stage)
        inputs = core.stage_inputs(times, tk_t)
        K_t, X_t = (torch.from_numpy(np.array(v)).reshape(*batch, *v.shape[-2:]) for v in (K, X))
        Z_t = K_t.new_zeros(*K_t.shape[:-1], 0)
        core.stack_stages = core.stacking_works(times, inputs, K_t, X_t, Z_t)


def _writable(a: np.ndarray) -> np.ndarray:
    """``a``, or a copy of it when it is a read-only view (``torch.from_numpy`` needs a
    writable array)."""
    return a if a.flags.writeable else a.copy()


def _inverse(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched inverse of (B, q, q) matrices and a (B,) mask of the singular ones (their
    entries are garbage and never used). One matrix goes to LAPACK's ``gesv`` directly (the
    routine ``np.linalg.inv`` runs, without its wrapper's overhead), a few
    to ``np.linalg.inv``, many to ``torch.linalg.inv_ex`` (:data:`_TORCH_INVERSE_MIN`)."""
    if M.shape[0] == 1:
        (gesv,) = get_lapack_funcs(("gesv",), (M,))
        _, _, inv, info = gesv(M[0], _identity(M.shape[-1], M.dtype.str))
        return inv[None], np.array([info != 0])
    if M.shape[0] < _TORCH_INVERSE_MIN:
        try:
            return np.linalg.inv(M), np.zeros(M.shape[0], dtype=bool)
        except np.linalg.LinAlgError:  # some member singular: per-member info below
            pass
    inv, info = torch.linalg.inv_ex(torch.from_numpy(M))
    return inv.numpy(), info.numpy() != 0


# From this many matrices on, torch's batched inverse beats numpy's loop over LAPACK calls
# (measured crossover: docs/benchmarks.md, ``bench_implicit``).
_TORCH_INVERSE_MIN = 32


@functools.lru_cache(maxsize=32)
def _identity(q: int, dtype: str) -> np.ndarray:
    """A read-only (q, q) identity (a right-hand side that ``gesv`` copies, never writes)."""
    eye = np.eye(q, dtype=dtype)
    eye.flags.writeable = False
    return eye


def _all(mask: np.ndarray) -> bool:
    """``mask.all()`` for a host bool array, without the method's Python-level wrapper."""
    return np.count_nonzero(mask) == mask.size


_any, _pick = ArrayOps.any, ArrayOps.pick


def one_trajectory(x0: torch.Tensor) -> bool:
    """Whether a problem that the numpy kernel runs takes :class:`OneTrajectoryKernel`: a
    single trajectory (``x0.numel() == n``) in float64 (the dtype of Python floats, so that
    its step control rounds as the batched one does)."""
    return x0.dtype == torch.float64 and x0.numel() == x0.shape[-1]


class NumpyKernel:
    """:class:`~integrators.radau.RadauKernel` on host (numpy) arrays with the flattened batch
    ``B`` as one axis: explicit ODEs on the CPU whose Newton matrix is inverted explicitly
    (:func:`host_loop_supported`). Only the user's model runs in torch (:class:`_HostModel`);
    the Newton matrix is inverted (:func:`_factorize`) and the simplified Newton iteration
    (:meth:`newton`) is one matrix product per iteration. The records of the accepted steps
    are replayed in torch for gradients at the end (:func:`_records`)."""

    scalar = False

    def __init__(self, core, x0, z0, xdot0, t, rtol, atol, newton_tol, max_iter):
        self.core, self.x0, self.z0 = core, x0, z0
        npdt = np.float64 if x0.dtype == torch.float64 else np.float32
        self.model = model = _HostModel(core, x0.shape[:-1], npdt)
        B, n = model.B, core.system.n
        # the tableau's constants: gamma e of the embedded estimate (see integrators.radau),
        # the error-filter weights, A, b, the nodes c (float64) and their Lagrange
        # coefficients for extrapolation_matrix, and the RMS factors of the error and Newton
        gamma, e = embedded_weights(core.tab)
        self.gamma_e = (gamma * e).astype(npdt)
        self.filt = _filter_weights(core, npdt)
        self.A, self.b = (np.array(v, dtype=npdt) for v in (core.tab.A, core.tab.b))
        self.c = np.array(core.c, dtype=np.float64)
        self.c_col = self.c[:, None]
        self.lagrange = lagrange_coefficients(tuple(self.c))
        self.rms, self.rms_newton = 1.0 / n**0.5, 1.0 / (core.s * n) ** 0.5
        self.t0 = t.detach().numpy().astype(npdt)[0]
        self.tiny = float(np.finfo(npdt).tiny)  # the dtype's smallest normal number
        # tolerances: floats, or (*batch, n | 1) tensors flattened to (B, n | 1)
        self.atol, self.rtol = (
            v.detach().cpu().numpy().astype(npdt).reshape(-1, v.shape[-1])
            if isinstance(v, torch.Tensor)
            else npdt(v)
            for v in (atol, rtol)
        )
        self.npdt, self.newton_tol, self.max_iter = npdt, newton_tol, max_iter
        self.x = x0.detach().numpy().astype(npdt).reshape(B, n)
        self.xdot = xdot0.detach().numpy().astype(npdt).reshape(B, n)
        self.z = z0.detach()
        self.G = self.J_inv = self.real_inv = self.prev_W = None
        self.n_jac = self.n_lu = 0
        self.accepted: list[tuple] = []  # per advancing iteration: what the records need

    def begin_step(self, tcur, h):
        B, s = self.model.B, self.core.s
        self.h = h.reshape(B)
        # t_k, t_k + h and the stage times t_k + c_i h, rounded as the torch kernel does
        host = np.empty((2 + s, B), dtype=self.npdt)
        tk = tcur.reshape(B)
        host[0], host[1], host[2:] = tk, tk + self.h, tk + self.c_col * self.h
        self.host = host

    def jacobian(self, mask):
        mask = np.reshape(mask, -1)  # (B,), also from the one-trajectory kernel's Python bool
        self.G = _jacobian(self.core, self.model, self.host[0], self.x, self.z, self.xdot,
                           mask, self.G)  # fmt: skip
        self.n_jac += 1
        return None

    def factorize(self, mask, h, h_fact):
        shape, mask, h = mask.shape, mask.reshape(-1), h.reshape(-1)
        # every member at h: all need it, or none was factorised yet (h_fact is 0 until then)
        if self.J_inv is None or _all(mask):
            self.J_inv, self.real_inv, sing = _factorize(self.A, self.filt, self.G, h)
            singular = mask & sing
        else:  # only the members that need it (finished members never do)
            idx = np.flatnonzero(mask)
            singular = np.zeros_like(mask)
            self.J_inv[idx], self.real_inv[idx], singular[idx] = _factorize(
                self.A, self.filt, self.G[idx], h[idx]
            )
        self.n_lu += 1
        return singular.reshape(shape)

    def newton(self, live, have_prev, ratio):
        """Simplified Newton on ``R(W) = K - f(t_k + c h, x_k + h A K)`` (eq. 7.14-7.16), per
        sample, as :meth:`IRKCore.newton` with ``predict=True``: converged when
        ``theta / (1 - theta) ||dW|| <= tol``, failed when ``theta >= 1`` or the rate predicts
        that ``max_iter`` iterations will not do. One product with ``J_inv`` (B, 2 s n, s n),
        ``-J^{-1}`` stacked over ``(A (x) I) (-J^{-1})``, gives the increment and its image
        ``A dK`` per iteration."""
        shape, model, h = live.shape, self.model, self.h
        tol, max_iter = self.newton_tol, self.max_iter
        self.sc_x = self.atol + self.rtol * np.abs(self.x)
        W = _stage_guess(self.c, self.lagrange, self.prev_W, have_prev.reshape(-1),
                         ratio.reshape(-1), self.xdot)  # fmt: skip
        t_stage, tk = model.times(self.host[2:]), self.host[0]  # (s, *batch, 1) tensor, (B,)
        B, s, n = W.shape
        sn = s * n
        # weights of the stage increments h (A dK)_i / sc_x, times the RMS factor: (B, s n)
        w = np.concatenate([h[:, None] / self.sc_x] * s, axis=1) * W.dtype.type(self.rms_newton)
        live = live.reshape(-1).copy()
        conv = np.zeros_like(live)
        non_finite = np.zeros_like(live)
        iters = np.zeros(B, dtype=np.int64)
        theta = np.zeros(B)
        norm_old = None
        hA = h[:, None, None] * self.A
        xk = self.x[:, None, :]
        for it in range(max_iter):
            X = hA @ W
            X += xk  # stage states (B, s, n)
            if model.core.stack_stages is None:
                model.decide_stacking(tk, h, t_stage, W, X)
            R = W - model.stages(t_stage, X.transpose(1, 0, 2), self.z).transpose(1, 0, 2)
            both = self.J_inv @ R.reshape(B, sn, 1)  # (dW, A dK) in one product
            v = both[:, sn:, 0] * w
            norm = np.sqrt(np.einsum("ij,ij->i", v, v)).astype(np.float64, copy=False)
            if not np.isfinite(norm.sum()):  # (a finite sum means every member is finite)
                bad = live & ~np.isfinite(norm)
                non_finite |= bad
                live &= ~bad
            if norm_old is None:
                done = live & (norm == 0)
            else:  # contraction theta; eta ||dW|| = theta / (1 - theta) ||dW|| <= tol converges
                th = norm / np.maximum(norm_old, self.tiny)
                np.copyto(theta, th, where=live)
                rate = norm / np.maximum(1.0 - th, 1e-12)
                # diverging, or predicted to miss tol within max_iter iterations: give up
                live &= (th < 1.0) & (th ** (max_iter - it) * rate <= tol)
                done = live & (th * rate <= tol)
            dW = both[:, :sn].reshape(B, s, n)
            np.add(W, dW, out=W, where=live[:, None, None])  # (W is this step's own array)
            iters += live
            conv |= done
            live &= ~done
            norm_old = norm
            if not _any(live):
                break
        self.W = W
        out = conv, iters, theta, non_finite
        return out if len(shape) == 1 else tuple(v.reshape(shape) for v in out)

    def error(self, ok, retry):
        shape, W, x = ok.shape, self.W, self.x
        self.Wg = W if np.isfinite(W.sum()) else np.nan_to_num(W)
        self.x_new = x_new = x + self.h[:, None] * (self.b @ self.Wg)  # eq. 7.18
        # filtered embedded error estimate (see integrators.radau), refined after rejections
        eK = self.gamma_e @ W
        err_x = (self.real_inv @ (self.xdot + eK)[:, :, None])[:, :, 0]
        retry = retry.reshape(-1)
        if _any(retry):
            f_err = self.model.f(self.host[0], x + err_x, self.z)
            err_retry = (self.real_inv @ (f_err + eK)[:, :, None])[:, :, 0]
            err_x = _pick(retry, err_retry, err_x)
        sc = np.maximum(self.sc_x, self.atol + self.rtol * np.abs(x_new))
        err = np.sqrt(np.square(err_x / sc).sum(-1)).astype(np.float64, copy=False) * self.rms
        finite = np.isfinite(x_new).all(-1) & np.isfinite(err)
        return np.where(finite, err, np.inf).reshape(shape), finite.reshape(shape)

    def advance(self, accept, tcur, h):
        accept = accept.reshape(-1)
        t_start = np.where(accept, tcur.reshape(-1), np.inf).astype(self.npdt)
        self.accepted.append((t_start, h.reshape(-1), accept, self.W, self.host, self.Wg, self.x))
        xdot_new = self.model.f(self.host[1], self.x_new, self.z)
        self.x = _pick(accept, self.x_new, self.x)
        self.xdot = _pick(accept, xdot_new, self.xdot)
        self.prev_W = self.W if self.prev_W is None else _pick(accept, self.W, self.prev_W)

    def records(self):
        return _records(self.core, self.model, self.x0, self.z0, self.t0, self.accepted)

    def step_mode(self):
        """No gradient recording (the records replay the steps for gradients), and not
        inference mode: models that call autograd inside ``f`` (Lagrangian systems,
        energy-based networks) need ``enable_grad`` to work there."""
        stack = contextlib.ExitStack()
        stack.enter_context(np.errstate(all="ignore"))
        stack.enter_context(torch.no_grad())
        return stack


class OneTrajectoryKernel(NumpyKernel):
    """:class:`NumpyKernel` for one float64 trajectory (:func:`one_trajectory`), driven by the
    loop's Python-scalar control (``scalar = True``): masks arrive as Python bools, times and
    step sizes as Python floats, and the results go back the same way. The states and stages
    stay numpy arrays shaped (1, ...), and the Jacobian, the factorisation, the records and
    the gradient replay are the numpy kernel's. The simplified Newton iteration
    (:func:`_newton_one`) and the error norm are written for one flat vector, with the norms
    and the convergence test in Python floats: the same iteration as :meth:`NumpyKernel.newton`, a
    deliberate kernel pair (the batched one is vectorised over samples, this one pays no
    per-array overhead)."""

    scalar = True

    def __init__(self, core, x0, z0, xdot0, t, rtol, atol, newton_tol, max_iter):
        super().__init__(core, x0, z0, xdot0, t, rtol, atol, newton_tol, max_iter)
        # tolerances of the one sample: (n,) or (1,) arrays, like its flat state vectors
        self.atol, self.rtol = (np.reshape(v, -1) for v in (self.atol, self.rtol))
        self.A_kron = np.kron(self.A, np.eye(core.system.n))
        self.accept_mask = np.ones(1, dtype=bool)
        self.powers = np.arange(core.s)

    def begin_step(self, tcur, h):
        self.h = h
        host = np.empty((2 + self.core.s, 1))  # t_k, t_k + h and the stage times t_k + c_i h
        host[0], host[1], host[2:, 0] = tcur, tcur + h, tcur + self.c * h
        self.host = host

    def factorize(self, mask, h, h_fact):
        self.J_inv, self.real_inv, singular = _factorize(self.A, self.filt, self.G, np.array([h]))
        self.n_lu += 1
        return bool(singular[0])

    def newton(self, live, have_prev, ratio):
        self.sc_x = self.atol + self.rtol * np.abs(self.x)
        if not live:
            return False, 0, 0.0, False
        if have_prev:  # previous stage polynomial at the new nodes 1 + c_i h / h_prev
            # extrapolation_matrix(c, ratio) written for one float ratio: per-array overhead
            # dominates at this size, and the step loop runs it every step
            tau = 1.0 + self.c * ratio
            W = ((tau[:, None] ** self.powers) @ self.lagrange) @ self.prev_W
        else:
            W = np.repeat(self.xdot[:, None, :], self.core.s, axis=1)
        self.W, conv, iters, theta, nonfin = _newton_one(
            self.model, self.A_kron, self.model.times(self.host[2:]), self.host[0], self.h,
            self.x, self.z, W, self.J_inv, self.sc_x, self.newton_tol, self.max_iter,
            self.rms_newton, self.tiny,
        )  # fmt: skip
        return conv, iters, theta, nonfin

    def error(self, ok, retry):
        W, x = self.W, self.x
        self.Wg = W if math.isfinite(W.sum()) else np.nan_to_num(W)
        self.x_new = x_new = x + self.h * (self.b @ self.Wg)  # eq. 7.18
        # filtered embedded error estimate (see integrators.radau), refined after rejections
        eK = self.gamma_e @ W[0]
        err_x = self.real_inv[0] @ (self.xdot[0] + eK)
        if retry:
            f_err = self.model.f(self.host[0], x + err_x, self.z)
            err_x = self.real_inv[0] @ (f_err[0] + eK)
        sc = np.maximum(self.sc_x[0], self.atol + self.rtol * np.abs(x_new[0]))
        q = err_x / sc
        err = math.sqrt(q @ q) * self.rms
        finite = math.isfinite(err) and (
            math.isfinite(x_new.sum()) or bool(np.isfinite(x_new).all())
        )
        return (err if finite else math.inf), finite

    def advance(self, accept, tcur, h):
        self.accepted.append(
            (np.array([tcur]), np.array([h]), self.accept_mask, self.W, self.host, self.Wg, self.x)
        )
        self.xdot = self.model.f(self.host[1], self.x_new, self.z)
        self.x = self.x_new
        self.prev_W = self.W


def _jacobian(core, model, tk, x, z, xdot, mask, G_old):
    """``G = -df/dx`` (B, n, n) at the step start for the ``mask`` samples (autograd, through
    :meth:`IRKCore.frozen_blocks`); the others keep ``G_old``."""
    with torch.no_grad():
        _, G_t, _, _ = core.frozen_blocks(model.times(tk), model.state(x), z, model.state(xdot))
    G = model.back(G_t, np.empty((model.B, *G_t.shape[-2:])))
    return G if G_old is None else _pick(mask, G, G_old)


def _filter_weights(core: IRKCore, npdt) -> np.ndarray:
    """``M`` ((s n)^2, n^2) with ``(lambda_0 / h I + G)^{-1} = h vec(J^{-1}) M``: the sum
    ``sum_ij w_ij (J^{-1})_ij`` over the (n, n) blocks of ``J^{-1}`` with
    ``w_ij = (V^{-1})_0i V_j0 / lambda_0`` for the eigenvectors ``V`` of ``A^{-1}`` (the
    transformation of ``StageLinearSolver``, whose dense path reads the error filter's block
    off ``J^{-1}`` the same way), as one matrix product."""
    solver, n = core.solver, core.system.n
    P_r, V_r = (v.detach().cpu().numpy().astype(np.float64) for v in (solver.P_r, solver.V_r))
    v_inv_row = P_r[0] @ np.array(core.tab.A)  # row 0 of V^{-1} = P A
    w = np.outer(v_inv_row, V_r[:, 0]) / solver.real_eigenvalue
    eye = np.eye(n)
    M = np.einsum("ij,ac,bd->iajbcd", w, eye, eye)  # M[(i, a, j, b), (c, d)] = w_ij d_ac d_bd
    return M.reshape(-1, n * n).astype(npdt)


def _kron_map(A: np.ndarray, n: int) -> np.ndarray:
    """``P`` (n^2, (s n)^2) with ``vec(A (x) G) = vec(G) @ P`` (cached per ``A`` and ``n``):
    every column has one nonzero ``a_ij``, so the entries are the exact products."""
    key = (A.tobytes(), A.dtype.str, n)
    if key not in _KRON_MAPS:
        units = np.eye(n * n, dtype=A.dtype).reshape(n * n, n, n)
        P = A[None, :, None, :, None] * units[:, None, :, None, :]  # (n^2, s, n, s, n)
        _KRON_MAPS[key] = P.reshape(n * n, -1)
    return _KRON_MAPS[key]


_KRON_MAPS: dict = {}


def _factorize(A, filt, G, h):
    """Inverse of the simplified-Newton matrix ``J = I + h A (x) G`` (eq. 7.16, ``G = -df/dx``)
    and the error filter's real block ``(lambda_0 / h I + G)^{-1}`` read off it.

    Args:
        A: (s, s); filt: ((s n)^2, n^2) :func:`_filter_weights`; G: (B, n, n); h: (B,).

    Returns:
        ``(-J^{-1}`` stacked over ``(A (x) I)(-J^{-1})`` (B, 2 s n, s n), so that one product
        gives the Newton increment and its stage-state image; the real block's inverse
        (B, n, n); a (B,) mask of singular members (a singular real block makes ``J``
        singular)).
    """
    B, n, s = G.shape[0], G.shape[-1], A.shape[0]
    sn = s * n
    hb = h[:, None, None]
    J = (G.reshape(B, n * n) @ _kron_map(A, n)).reshape(B, sn, sn)
    J *= hb
    J.reshape(B, sn * sn)[:, :: sn + 1] += 1.0  # + I
    inv, sing = _inverse(J)
    inv_r = (inv.reshape(B, -1) @ filt).reshape(B, n, n) * hb
    out = np.empty((B, 2 * s * n, s * n), dtype=inv.dtype)
    np.negative(inv, out=out[:, : s * n])
    # (A (x) I) (-J^{-1}): block row i is sum_j a_ij (block row j of -J^{-1})
    np.matmul(A, out[:, : s * n].reshape(B, s, n * s * n), out=out[:, s * n :].reshape(B, s, -1))
    return out, inv_r, sing


def _stage_guess(c, lagrange, prev_W, have_prev, ratio, xdot):
    """Newton start (B, s, n): the previous step's stage polynomial ``sum_j W_j l_j(tau)``
    at the new nodes ``tau_i = 1 + c_i h_new / h_old`` (:func:`extrapolation_matrix`), else
    ``x'_k`` at every stage."""
    s = len(c)
    if not _any(have_prev):
        return np.repeat(xdot[:, None, :], s, axis=1)
    ext = (extrapolation_matrix(c, ratio, lagrange) @ prev_W).astype(prev_W.dtype, copy=False)
    if _all(have_prev):
        return ext
    return _pick(have_prev, ext, np.repeat(xdot[:, None, :], s, axis=1))


def _newton_one(model, A_kron, t_stage, tk, h, xk, z, W, J_inv, sc_x, tol, max_iter, rms, tiny):
    """:meth:`NumpyKernel.newton` for one trajectory (:class:`OneTrajectoryKernel`):
    simplified Newton on ``R(W) = K - f(t_k + c h, x_k + h A K)`` (eq. 7.14-7.16) on flat
    stage vectors, with the same stopping and divergence rules.

    Args:
        A_kron: (s n, s n) ``A (x) I``; t_stage: (s, *batch, 1) stage-time tensor; tk: (1,)
            host step start; h: step size; xk, sc_x: (1, n); W: (1, s, n) initial guess;
            z: the (empty) algebraic state tensor; J_inv: (1, 2 s n, s n) ``-J^{-1}`` stacked
            over ``(A (x) I) (-J^{-1})``; rms: ``1 / sqrt(s n)``; tiny: smallest normal float64.

    Returns:
        ``(W, converged, iterations, theta, non_finite)``.
    """
    _, s, n = W.shape
    sn = s * n
    J = J_inv[0]
    hA = h * A_kron
    x_rep = np.concatenate((xk[0],) * s)  # x_k at every stage, (s n,)
    w = np.concatenate(
        (h / sc_x[0] * rms,) * s
    )  # weights of the stage increments h (A dK)_i / sc_x
    Wv = W.reshape(sn)
    theta, norm_old = 0.0, None
    for it in range(max_iter):
        X = hA @ Wv
        X += x_rep  # stage states, stage-major (s n,)
        if model.core.stack_stages is None:
            K1, X1 = Wv.reshape(1, s, n), X.reshape(1, s, n)
            model.decide_stacking(tk, np.array([h]), t_stage, K1, X1)
        F = model.stages(t_stage, X.reshape(s, 1, n), z)
        both = J @ (Wv - F.reshape(sn))  # (dW, A dK) in one product
        v = both[sn:] * w
        norm = math.sqrt(v @ v)
        if not math.isfinite(norm):
            return Wv.reshape(1, s, n), False, it, theta, True
        if norm_old is None:
            done = norm == 0.0
        else:  # contraction theta; theta / (1 - theta) ||dW|| <= tol converges
            th = norm / max(norm_old, tiny)
            theta = th
            rate = norm / max(1.0 - th, 1e-12)
            # diverging, or predicted to miss tol within max_iter iterations: give up
            if not (th < 1.0 and th ** (max_iter - it) * rate <= tol):
                return Wv.reshape(1, s, n), False, it, theta, False
            done = th * rate <= tol
        Wv = Wv + both[:sn]
        if done:
            return Wv.reshape(1, s, n), True, it + 1, theta, False
        norm_old = norm
    return Wv.reshape(1, s, n), False, max_iter, theta, False


def _records(core, model, x0, z0, t0, accepted):
    """:class:`StepRecords` (dense output) of the accepted steps, one record per driver
    iteration that advanced a sample, as the torch driver keeps them.

    Values come from the host loop (the step-start states and converged stages it kept).
    In grad mode the steps are also replayed in torch, ``x_{k+1} = x_k + h sum_i b_i K_i``
    (eq. 7.18) with implicit-function-theorem stages (:meth:`IRKCore.ift`, which decides per
    step whether the stages carry gradients, as in the torch driver), and each recorded state
    is the host value plus the replay's zero-valued ``x - stop_grad(x)``: the torch driver's
    gradients, and outputs identical with and without autograd."""
    batch, s, n = model.batch, core.s, core.system.n
    hshape = host_shape(batch)
    records = StepRecords(core.tab, n)
    start = np.full(batch, t0, dtype=model.npdt)
    records.append(start, np.ones(batch, dtype=model.npdt), x0, x0.new_zeros(*batch, s, n), z0)
    with_grad = torch.is_grad_enabled()
    x = x0  # the replayed step-start state while it carries a graph, else None
    for t_start, h, accept, W, host, Wg, x_host in accepted:
        t_start, h_rec = t_start.reshape(batch), h.reshape(batch)
        W_t = torch.from_numpy(Wg).reshape(*batch, s, n)
        x_rec = torch.from_numpy(x_host).reshape(*batch, n)
        if with_grad:
            xk = x_rec if x is None else x
            h_t, mask = torch.from_numpy(h_rec), accept.reshape(hshape)
            tk = model.times(host[0])
            times = core.stage_times(tk, h_t[..., None], len(batch), stacked=model.times(host[2:]))
            inputs = core.stage_inputs(times, tk)
            W_t = core.ift(times, inputs, h_t, xk, torch.from_numpy(W).reshape(W_t.shape), mask)
            if xk.requires_grad or W_t.requires_grad:
                x_rec = x_rec + (xk - xk.detach())
                x = masked_update(mask, core.step_end(xk, h_t, W_t), xk)
            else:  # nothing to carry: the next step starts from the host's state
                x = None
        records.append(t_start, h_rec, x_rec, W_t, z0)
    return records
