"""Fixed-step explicit Runge-Kutta for any explicit Butcher tableau (notes eq. 6.26).

For one step of size ``h`` from ``(t_k, x_k)``:

    K_i     = f(t_k + c_i h, x_k + h * sum_{j<i} a_ij K_j),   i = 1..s
    x_{k+1} = x_k + h * sum_i b_i K_i

The output grid ``t`` (T,) may be non-uniform; each interval ``[t_k, t_{k+1}]`` is split into
``substeps`` equal steps. Sampled inputs are held (zero-order hold, eq. 8.34) or interpolated
linearly *per interval*: every stage of a step inside ``[t_k, t_{k+1}]`` sees ``u_k`` (ZOH),
including stages with ``c_i = 1``.

Speed: the tableau is turned into Python-float coefficients once, zero coefficients are
skipped, and stages that neither ``b`` nor a later needed stage uses are not evaluated (e.g.
the FSAL stage of dopri5 at fixed step). The time loop runs in chunks of several steps; a
chunk is a plain Python function that can be compiled with ``torch.compile`` (fusing the
model ``f`` and the stage sums into one kernel). Compiling, its cache per model (the one-off
compile time is paid once per model and shape, reported in ``stats.extra["compile_s"]``) and
its eager fallbacks live in ``_fast`` (``_fast.compiled_stepper``).

Component-major layout: a model written component by component (``x1, x2 = x.unbind(-1)``
... ``torch.stack([...], -1)``, the zoo's plants) would make inductor write every stage into
an interleaved (*batch, nx) buffer, one scalar loop per stage. Compiled runs without autograd
of such a model (detected once by tracing it, ``_fast.cat_forwarding.reads_only_components``)
keep the state as a contiguous (nx, *batch) tensor, form each stage state component by
component, and compile with a graph pass that reads the model's stacked pieces where they
were computed (``_fast.cat_forwarding``): all stages of a step then fuse into one vectorised
loop over the batch (several times faster per step on large batches; timings in
docs/benchmarks.md). Models that mix components in matrix products keep the interleaved
layout, which suits them better.

Outputs are collected time-major (without autograd, in one preallocated buffer, on huge
pages when it is large: see ``_fast.buffers``) and returned as a (*batch, T, nx) view of it:
no strided copy per output. Finiteness costs nothing per
step: a non-finite state stays non-finite under ``x_{k+1} = x_k + h sum_i b_i K_i``
(inf + finite = inf, inf - inf = nan), so one check of the final state (the only host
synchronisation) finds the failed samples, and only then are their outputs searched.

Failure handling: a sample whose state becomes inf/nan gets ``Status.NON_FINITE`` and its
outputs from the first non-finite output time on are NaN (the other samples are unaffected:
batch members are independent). ``Solution.messages`` names
the sample index and the time interval where it happened. With autograd, the inf/nan of a
failed sample would still reach the gradient of shared parameters through ``f``'s own
backward (``0 * inf = nan``), even where the loss reads only finite outputs; so the steps
from the interval of the first failure on are run again with each failed sample frozen from
its failing interval on: its stages evaluate ``f`` at its (finite) initial state, and its
outputs there are NaN through a ``torch.where`` that passes no gradient to them.

Memory with autograd: the graph of every step is kept for the backward pass. Its size is
measured on the run's second chunk of steps (saved-tensor bytes and graph nodes) and
extrapolated before the remaining steps run; a run that would not fit raises
``GraphMemoryError``. ``checkpoint=`` runs the steps in segments under
``torch.utils.checkpoint`` whose saved tensors are recomputed in the backward pass.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from ._fast import available_bytes, compiled_stepper, empty_buffer
from ._fast import clear_compile_cache as clear_compile_cache
from ._options import check_flag, check_int, raise_shape_change
from .errors import GraphMemoryError, TableauError
from .inputs import BoundRHS
from .jacobians import graph_nodes
from .solution import Solution, SolverStats, Status

#: Steps per compiled chunk (the chunk is unrolled; more steps = longer compile).
CHUNK_STEPS = 8
#: Big states get fewer steps per compiled chunk, ``CHUNK_STATE_BYTES // state bytes``: an
#: interleaved chunk keeps every stage of every step in its own buffer, which should stay in
#: cache, and a component-major chunk's outputs of several steps do not fuse into one loop
#: (the measurements behind the value: docs/benchmarks.md, "Tuning constants").
CHUNK_STATE_BYTES = 2**20
#: A run with autograd may plan to keep at most this fraction of the available memory
#: (``_fast.buffers.available_bytes``) for its graph and outputs (``_check_graph_memory``).
GRAPH_MEMORY_FRACTION = 0.9
#: Bytes of autograd bookkeeping per graph node (the node, its saved-variable and tensor
#: objects), besides the saved tensors' data. Fitted to the memory of eager RK4 steps of two
#: models (Van der Pol: 40 nodes and 20 saved tensors per step, 38 kB; a linear model
#: x @ A.T: 24 nodes and 8 saved tensors, 23 kB): about 1 kB per node.
GRAPH_NODE_OVERHEAD = 1024


@dataclass(frozen=True)
class _Scheme:
    """An explicit tableau as Python floats, with unused stages and zero entries removed.

    ``stages`` are the indices of evaluated stages in order; ``a[n]`` lists the non-zero
    ``(position in stages, a_ij)`` of stage ``stages[n]``; ``b`` the non-zero
    ``(position, b_i)``; ``c[n]`` the node of stage ``stages[n]``.
    """

    stages: tuple[int, ...]
    a: tuple[tuple[tuple[int, float], ...], ...]
    b: tuple[tuple[int, float], ...]
    c: tuple[float, ...]

    @classmethod
    def from_tableau(cls, tab) -> _Scheme:
        A, b, c = tab.A, tab.b, tab.c
        s = tab.stages
        needed = [bool(b[i] != 0.0) for i in range(s)]
        for i in range(s - 1, -1, -1):  # a stage is needed if a needed later stage uses it
            if needed[i]:
                for j in range(i):
                    if A[i, j] != 0.0:
                        needed[j] = True
        stages = tuple(i for i in range(s) if needed[i])
        pos = {i: n for n, i in enumerate(stages)}
        a = tuple(
            tuple((pos[j], float(A[i, j])) for j in range(i) if A[i, j] != 0.0) for i in stages
        )
        return cls(
            stages=stages,
            a=a,
            b=tuple((pos[i], float(b[i])) for i in stages if b[i] != 0.0),
            c=tuple(float(c[i]) for i in stages),
        )


def _lincomb(x, h, terms, component_major: bool = False):
    """``x + h * sum(coef * K)`` with Python-float coefficients.

    With a float ``h`` (eager chunks) one ``add(..., alpha=)`` per term. With a tensor ``h``
    (compiled chunks, where ``alpha`` cannot hold it) plain products and sums.

    With ``component_major``, ``x`` is the list of the state's nx (*batch) components and the
    result the list of the new ones: each component is combined on its own from the
    ``K[..., i]``. A stage state stacked from them is what the compiled chunk's graph pass
    (``_fast.cat_forwarding``) turns into reads of the pieces of ``f``'s own ``stack``: no
    interleaved stage buffers.
    """
    if component_major:
        return [_lincomb(xi, h, [(coef, K[..., i]) for coef, K in terms]) for i, xi in enumerate(x)]
    if not terms:
        return x
    if isinstance(h, float):
        out = x
        for coef, K in terms:
            out = torch.add(out, K, alpha=h * coef)
        return out
    acc = None
    for coef, K in terms:
        acc = K * coef if acc is None else acc + K * coef
    return x + h * acc


def _make_chunk(
    f, kind, u_fn, scheme: _Scheme, substeps: int, n_out: int, component_major=False, steps=None
):
    """A function advancing ``n_out`` output intervals of ``substeps`` steps each.

    chunk(x, t_stage, h, h_float, u0, du, out=None, frozen=None) -> (x_last, outputs)
        x: (*batch, nx) state at the chunk start, or (nx, *batch) with ``component_major``.
        t_stage: (n_out * substeps, n_stages) stage times.
        h: (n_out * substeps,) step sizes (tensor, used when h_float is None).
        h_float: tuple of Python-float step sizes, or None (compiled chunks).
        u0, du: (..., n_out, nu) input at the interval start and its increment over the
            interval (du is None for zero-order hold), or None.
        out: optional (n_out, *batch, nx) buffer slice ((n_out, nx, *batch) with
            ``component_major``, no autograd) that receives the states at the output times in
            place; a compiled chunk then writes them straight from its fused kernel instead of
            allocating (and page-faulting) a fresh tensor per call.
        frozen: None, or ``(mask, x_safe)``: a (*batch, 1) bool mask of frozen samples and a
            finite (*batch, nx) state; every stage of a frozen sample evaluates ``f`` at
            ``x_safe`` instead of its own state (see ``solve_explicit``, failed samples).
    Returns the state at the chunk end and the states at the output times, time-major
    ((n_out, *batch, nx) or (n_out, nx, *batch); ``out`` when given).

    ``steps = (j0, j1)`` (with ``n_out == 1``) takes only the substeps ``j0 .. j1 - 1`` of the
    interval (checkpointed segments that end inside an interval); the returned "outputs" are
    then the state after substep ``j1 - 1``, an output only when ``j1 == substeps``.

    ``component_major`` keeps the state as its nx components (rows of a (nx, *batch) tensor)
    and forms every stage state component by component (:func:`_lincomb`). ``f`` still
    receives and returns (*batch, nx) tensors; the layout only changes which reads inductor
    sees, so that with the cat-forwarding pass all stages of a component-wise model fuse into
    one contiguous, vectorised loop.
    """
    stages = scheme.stages
    a, b, c = scheme.a, scheme.b, scheme.c
    m = substeps
    j0, j1 = (0, m) if steps is None else steps

    def chunk(x, t_stage, h, h_float, u0, du, out=None, frozen=None):
        if component_major:
            x = list(x.unbind(0))
        outputs = []
        for q in range(n_out):
            if kind == "zoh":
                uq = u0[..., q, :]
            elif kind == "linear":
                uq, dq = u0[..., q, :], du[..., q, :]
            for j in range(j0, j1):
                n = q * (j1 - j0) + j - j0
                hn = h[n] if h_float is None else h_float[n]
                tn = t_stage[n]
                K = []
                for p in range(len(stages)):
                    xs = _lincomb(x, hn, [(coef, K[r]) for r, coef in a[p]], component_major)
                    if component_major:
                        xs = torch.stack(xs, dim=-1)
                    if frozen is not None:
                        xs = torch.where(frozen[0], frozen[1], xs)
                    ts = tn[p]
                    if kind == "none":
                        K.append(f(ts, xs))
                    elif kind == "callable":
                        K.append(f(ts, xs, u_fn(ts)))
                    elif kind == "zoh":
                        K.append(f(ts, xs, uq))
                    else:
                        theta = (j + c[p]) / m
                        us = uq if theta == 0.0 else uq + dq * theta
                        K.append(f(ts, xs, us))
                    if K[-1].shape != xs.shape:  # a static shape: free when compiled
                        raise_shape_change(K[-1], xs, ts)
                x = _lincomb(x, hn, [(coef, K[r]) for r, coef in b], component_major)
            outputs.append(torch.stack(x, dim=0) if component_major else x)
        x = outputs[-1]
        if out is None:
            return x, torch.stack(outputs, dim=0)
        out.copy_(outputs[0].unsqueeze(0) if n_out == 1 else torch.stack(outputs, dim=0))
        return x, out

    return chunk


def _outputs_per_chunk(x0: torch.Tensor, substeps: int) -> int:
    """Output intervals per compiled chunk: ``CHUNK_STEPS`` steps, fewer for big states
    (``CHUNK_STATE_BYTES``), at least one interval of ``substeps`` steps."""
    state_bytes = max(1, x0.numel() * x0.element_size())
    steps = min(CHUNK_STEPS, max(1, CHUNK_STATE_BYTES // state_bytes))
    return max(1, steps // substeps)


def _count_saved(storages: dict):
    """A ``saved_tensors_hooks`` pack hook recording ``storages[address] = bytes`` of every
    tensor autograd saves."""

    def pack(tensor):
        storage = tensor.untyped_storage()
        storages[storage.data_ptr()] = storage.nbytes()
        return tensor

    return pack


def _segment_steps(checkpoint, n_steps: int, chunk_steps: int) -> int | None:
    """Steps per checkpointed segment: None (no checkpointing) for ``False``, the integer
    itself, or for ``True`` about ``sqrt(n_steps)`` (rounded up to whole chunks of
    ``chunk_steps`` steps where a chunk is shorter)."""
    if checkpoint is False:
        return None
    if checkpoint is not True:
        return int(checkpoint)
    steps = math.isqrt(max(n_steps - 1, 0)) + 1
    return -(-steps // chunk_steps) * chunk_steps if chunk_steps <= steps else steps


def _graph_bytes(data: float, nodes: float, n_left: int, seg_steps, state_bytes: int, T: int):
    """Estimated bytes a run with autograd still allocates for its gradient.

    Per step, autograd saves ``data`` bytes of tensors and creates ``nodes`` graph nodes of
    about :data:`GRAPH_NODE_OVERHEAD` bytes each. Checkpointed segments of ``seg_steps``
    steps keep the data of one segment (recomputed in the backward pass) and the segments'
    start states, but the nodes of every step (non-reentrant checkpointing drops the saved
    data only). Three copies of the (T, *batch, nx) outputs are added: the pieces, their
    concatenation and its gradient.
    """
    outputs = 3 * T * state_bytes
    bookkeeping = nodes * GRAPH_NODE_OVERHEAD * n_left
    if seg_steps is None:
        return data * n_left + bookkeeping + outputs
    starts = -(-n_left // seg_steps) * state_bytes
    return data * min(seg_steps, n_left) + starts + bookkeeping + outputs


def _check_graph_memory(data, nodes, n_left, seg_steps, state_bytes, T, device) -> None:
    """Raise GraphMemoryError when the graph of the remaining ``n_left`` steps
    (:func:`_graph_bytes`) exceeds :data:`GRAPH_MEMORY_FRACTION` of the available memory."""
    avail = available_bytes(device)
    if avail is None:
        return
    if torch.device(device).type != "cpu":
        nodes = 0.0  # the graph's nodes live in host memory, not on the device
    need = _graph_bytes(data, nodes, n_left, seg_steps, state_bytes, T)
    budget = GRAPH_MEMORY_FRACTION * avail
    if need <= budget:
        return
    gib = 2.0**30
    seg_auto = _segment_steps(True, n_left, 1)
    need_ck = _graph_bytes(data, nodes, n_left, seg_auto, state_bytes, T)
    if seg_steps is None and need_ck <= budget:
        hint = (
            f"odeint(..., checkpoint=True) would need about {need_ck / gib:.3g} GiB (segments "
            f"of {seg_auto} steps recomputed in the backward pass, about twice the compute)"
        )
    elif seg_steps is None:
        hint = f"even checkpoint=True would need about {need_ck / gib:.3g} GiB"
    else:
        hint = f"with checkpoint=True (segments of {seg_auto} steps): {need_ck / gib:.3g} GiB"
    raise GraphMemoryError(
        f"the autograd graph of this fixed-step run would need about {need / gib:.3g} GiB "
        f"({data:.4g} bytes of saved tensors and {nodes:.3g} graph nodes per step for {n_left} "
        f"more steps, plus the outputs: {T} times x {state_bytes} bytes), but only "
        f"{avail / gib:.3g} GiB are available on {device}. Remedies: run under "
        "torch.no_grad() if no gradient is needed; request fewer output times, a shorter "
        f"horizon or a smaller batch; {hint}."
    )


def solve_explicit(
    rhs,
    x0: torch.Tensor,
    t: torch.Tensor,
    tab,
    *,
    substeps: int = 1,
    compile="auto",
    checkpoint=False,
) -> Solution:
    """Fixed-step explicit Runge-Kutta on the grid ``t`` (notes eq. 6.26).

    Args:
        rhs: a :class:`~integrators.inputs.BoundRHS` from ``bind_rhs`` or any ``rhs(t, x)``;
            it receives 0-dim tensor times.
        x0: (*batch, nx) initial states (validated by the caller).
        t: (T,) strictly increasing output times, same dtype/device as ``x0``.
        tab: an explicit :class:`~integrators.tableau.ButcherTableau` (``b_err`` is ignored).
        substeps: integer number of equal steps per output interval (>= 1).
        compile: True (``torch.compile`` the chunked step, eager fallback if compilation
            fails), False, or ``"auto"``: compile once the eager runs of this model and state
            shape, over all calls and this run's predicted eager time included, reach
            ``_fast.compiled.AUTO_COMPILE_EAGER_SECONDS`` (rent-or-buy; a run compiles from
            its start, or for the rest of it once its first steps, extrapolated, say so).
        checkpoint: with autograd, ``False`` keeps every step's graph; ``True`` runs the
            steps in segments of about ``sqrt(n_steps)`` steps under
            ``torch.utils.checkpoint`` (non-reentrant), whose saved tensors the backward pass
            recomputes one segment at a time: the memory of the saved tensors then grows with
            about the square root of the number of steps, for about twice the compute; an
            integer ``k >= 1`` sets the steps per segment. Segments run eager (not compiled)
            chunks. The graph's nodes (about 1 kB each, some 40 per RK4 step of a small model)
            and the outputs are still kept for every step, so checkpointing pays off once the
            state holds more than a few hundred numbers. Ignored without autograd. A model
            that calls ``torch.autograd.grad`` inside ``f`` reads tensors its own graph saved
            at once, which under the checkpoint's hooks recomputes the segment so far at each
            such call (a cost growing with the square of the segment); it should keep its
            graph's tensors (``torch.autograd.graph.saved_tensors_hooks`` with identity
            functions around its body), as the Lagrangian systems of ``sysid.mechanics`` do:
            checkpointing then saves little for it.

    Returns:
        Solution with ``x`` (*batch, T, nx) (a view of a time-major (T, *batch, nx) buffer,
        or of a (T, nx, *batch) one for ``"component-major"`` runs; not contiguous: call
        ``.contiguous()`` where a contiguous tensor is needed), per-sample ``status``
        (SUCCESS or NON_FINITE) and ``stats`` (n_steps, n_f_evals; ``extra["compiled"]``,
        ``extra["compile_fallback"]`` why a requested compiled run went eager, else None,
        ``extra["compile_s"]`` the wall time of calls that triggered a compilation, else 0;
        ``extra["compiled_from_step"]`` the step from which chunks ran compiled (0: the whole
        run; later: ``"auto"`` decided during the run), None for an eager run;
        ``extra["layout"]``: ``"component-major"`` for compiled runs without autograd of a
        component-wise model with at most ``_fast.compiled.COMPONENT_MAJOR_MAX_STATES``
        states, else ``"interleaved"``; ``extra["checkpoint_steps"]``: steps per checkpointed
        segment or None).

    A sample whose state becomes non-finite does not poison the gradient of the others: with
    autograd the steps from the interval of the first failure on are run again with every
    failed sample frozen at its (finite) initial state from its failing interval on, so no
    inf/nan enters the graph (the outputs are the same; see the module docstring).

    Raises:
        TableauError: for an implicit tableau.
        InputValidationError: for ``substeps`` that is not an integer >= 1, ``compile`` that
            is not True, False or "auto", or a model whose output shape differs from the
            state's at some stage evaluation; ``checkpoint`` that is neither a bool nor an
            integer >= 1.
        GraphMemoryError: with autograd, when the graph of the run (measured on its second
            chunk of steps: the bytes autograd saves and the graph nodes it creates,
            extrapolated, see ``_graph_bytes``) would exceed
            :data:`GRAPH_MEMORY_FRACTION` of the available memory; raised after at most
            2 * :data:`CHUNK_STEPS` steps.
    """
    if not tab.is_explicit:
        raise TableauError(
            f"tableau {tab.name!r} is implicit (a_ij != 0 for some j >= i); fixed-step explicit "
            "integration needs a strictly lower-triangular A. Use odeint(..., method=tab), "
            "which dispatches implicit tableaus to the implicit solver."
        )
    m = check_int(substeps, "substeps")
    compile = check_flag(compile, "compile", allow=("auto",))
    if isinstance(checkpoint, (bool, np.bool_)):
        checkpoint = bool(checkpoint)
    else:
        checkpoint = check_int(checkpoint, "checkpoint (True, False or steps per segment)")
    scheme = _Scheme.from_tableau(tab)
    if isinstance(rhs, BoundRHS):
        f, kind, u_fn = rhs.f, rhs.kind, rhs.u
    else:
        f, kind, u_fn = rhs, "none", None
    batch = x0.shape[:-1]
    T = t.shape[0]
    n_int = T - 1
    n_steps = n_int * m

    # Per-step start times, sizes and stage times, computed once, vectorised.
    frac = torch.arange(m, dtype=t.dtype, device=t.device) / m
    h = ((t[1:] - t[:-1]) / m).repeat_interleave(m)  # (n_steps,)
    t_start = (t[:-1, None] + (t[1:] - t[:-1])[:, None] * frac).reshape(-1)
    c = torch.tensor(scheme.c, dtype=t.dtype, device=t.device)
    t_stage = t_start[:, None] + h[:, None] * c  # (n_steps, n_stages)
    # Python-float steps for the eager chunks (``add(..., alpha=)``), unless t is differentiated
    h_list = None if t.requires_grad else tuple(h.tolist())

    u0 = du = None
    if kind in ("zoh", "linear"):
        u0 = rhs.samples[..., :-1, :]
        if kind == "linear":
            du = rhs.samples[..., 1:, :] - u0

    t0 = t[0].detach()

    def f_at_start(x):
        """``f`` at the first output time with its input there (traced for the layout)."""
        if kind == "none":
            return f(t0, x)
        return f(t0, x, u_fn(t0) if kind == "callable" else u0[..., 0, :])

    def stepper(mode):
        return compiled_stepper(
            f,
            (id(tab), tab.A.tobytes(), tab.b.tobytes(), kind, id(u_fn), m),
            compile=mode,
            x0=x0,
            make_chunk=lambda slots, n, major: _make_chunk(
                slots[0], kind, slots[1], scheme, m, n, major
            ),
            callables=(f, u_fn),
            n_out=_outputs_per_chunk(x0, m),
            f_at_start=f_at_start,
            n_steps=n_steps,
        )

    fast = n_out_chunk = component_major = chunk_eager = tail_eager = None

    def use(new):
        """Run the chunks of the Stepper ``new``: its chunk length and state layout."""
        nonlocal fast, n_out_chunk, component_major, chunk_eager, tail_eager
        fast, n_out_chunk, component_major = new, new.n_out, new.component_major
        chunk_eager = _make_chunk(f, kind, u_fn, scheme, m, n_out_chunk)
        tail_eager = chunk_eager if n_out_chunk == 1 else _make_chunk(f, kind, u_fn, scheme, m, 1)

    use(stepper(compile))
    compiled_from = 0 if fast.active else None  # the step from which chunks may run compiled
    grad_mode = torch.is_grad_enabled()
    seg_steps = _segment_steps(checkpoint, n_steps, n_out_chunk * m) if grad_mode else None

    # Component-major runs keep the state as a contiguous (nx, *batch) tensor and the outputs
    # in a (T, nx, *batch) buffer; ``to_state`` views either as the (*batch, nx) the eager
    # chunks (tail, fallback) and the caller use.
    def to_state(y, lead=0):
        return y.movedim(lead, -1) if component_major else y

    def chunk_layout(x):
        return x.movedim(-1, 0).contiguous() if component_major else x

    def output_buffer():
        shape = (T, x0.shape[-1], *batch) if component_major else (T, *x0.shape)
        return empty_buffer(shape, x0.dtype, x0.device)

    x = chunk_layout(x0)
    # With autograd the per-chunk outputs are kept and concatenated at the end; without it
    # the chunks write into one preallocated time-major buffer (half the memory, no big cat).
    buffer = None
    if not grad_mode:
        buffer = output_buffer()
        to_state(buffer, 1)[0] = x0
    partial_chunks: dict = {}
    x_safe = x0.detach()  # where frozen samples evaluate f (finite: validated by odeint)

    def step_chunk(x, s, s_end, fail_interval=None, compiled_ok=True):
        """One chunk from step ``s`` (at most to step ``s_end``) from the state ``x`` (chunk
        layout): ``n_out_chunk`` output intervals (compiled where enabled), one interval, or
        part of one. ``fail_interval`` (*batch,) freezes the samples with
        ``fail_interval <= k`` in interval ``k`` (eager single intervals only).
        ``compiled_ok=False`` runs eager chunks only: a checkpointed segment is recomputed
        with dynamo disabled, and the recomputation must save the same tensors as the forward.

        Returns (x, step reached, outputs (n, *batch, nx) or None when no output time was
        reached or a buffer receives them).
        """
        k, j = divmod(s, m)
        full = fail_interval is None and j == 0 and k + n_out_chunk <= n_int
        full = full and s + n_out_chunk * m <= s_end
        if full or (j == 0 and s + m <= s_end):
            n_c = n_out_chunk if full else 1
            s_new, n_y = s + n_c * m, n_c
            fn = chunk_eager if full else tail_eager
        else:  # a checkpointed segment or the probe ends inside the interval
            j_end = min(m, j + s_end - s)
            s_new, n_y = s + j_end - j, int(j_end == m)
            if (j, j_end) not in partial_chunks:
                part = _make_chunk(f, kind, u_fn, scheme, m, 1, steps=(j, j_end))
                partial_chunks[j, j_end] = part
            fn = partial_chunks[j, j_end]
        k_end = k + max(n_y, 1)
        us = None if u0 is None else u0[..., k:k_end, :]
        ds = None if du is None else du[..., k:k_end, :]
        out = None if buffer is None or n_y == 0 else buffer[k + 1 : k + 1 + n_y]
        if full and compiled_ok:
            done = fast(x, t_stage[s:s_new], h[s:s_new], None, us, ds, out)
            if done is not None:
                return done[0], s_new, to_state(done[1], 1)
        hf = None if h_list is None else h_list[s:s_new]
        out_state = None if out is None else to_state(out, 1)
        frozen = None
        if fail_interval is not None:
            frozen = ((fail_interval <= k).unsqueeze(-1), x_safe)
        x_state, ys = fn(to_state(x), t_stage[s:s_new], h[s:s_new], hf, us, ds, out_state, frozen)
        x = x_state.movedim(-1, 0) if component_major else x_state
        return x, s_new, ys if n_y else None

    def compile_rest(x, s, eager_s):
        """Switch an eager ``"auto"`` run, ``eager_s`` seconds and ``s`` steps in, to compiled
        chunks; returns the state ``x`` in their layout. Without autograd ``s`` is at an
        output time, and the outputs so far move to a buffer of the new layout."""
        nonlocal buffer, compiled_from
        fast.add_eager_seconds(eager_s, s)
        use(stepper(True))
        compiled_from = s
        if buffer is not None and component_major:
            reached = s // m + 1
            moved, buffer = buffer, output_buffer()
            to_state(buffer, 1)[:reached] = moved[:reached]
        return chunk_layout(x)

    def segment(x, s, s_end, fail_interval):
        """Steps ``s .. s_end - 1``: the final state and the outputs reached (or None)."""
        ys = []
        while s < s_end:
            x, s, y = step_chunk(x, s, s_end, fail_interval, compiled_ok=False)
            if y is not None:
                ys.append(y)
        return x, (torch.cat(ys) if ys else None)

    def run(x, s, fail_interval=None):
        """Steps ``s .. n_steps - 1`` from ``x``. Returns the final state and, with autograd,
        the pieces ``(step reached, state there, outputs or None)``.

        With autograd the first two chunks (at most ``CHUNK_STEPS`` steps each) run under a
        hook that counts the bytes autograd saves; the second chunk's new saved bytes and
        graph nodes per step, extrapolated, must fit in the available memory
        (:func:`_check_graph_memory`). Later steps run in checkpointed segments of
        ``seg_steps`` steps when asked for (eager chunks: see ``step_chunk``).
        """
        pieces: list = []
        probes: list = []
        s_start, tic = s, time.perf_counter()
        while s < n_steps:
            probing = fail_interval is None and grad_mode and len(probes) < 2
            if probing:
                saved: dict = {}
                s_end = min(n_steps, s + min(n_out_chunk * m, CHUNK_STEPS))
                s0 = s
                with torch.autograd.graph.saved_tensors_hooks(_count_saved(saved), lambda t: t):
                    x, s, ys = step_chunk(x, s, s_end)
                nodes = set(graph_nodes(x))
                probes.append((saved, nodes))
                if len(probes) == 2 and s < n_steps and x.requires_grad:
                    data = sum(b for ptr, b in saved.items() if ptr not in probes[0][0])
                    _check_graph_memory(
                        data / (s - s0),
                        len(nodes - probes[0][1]) / (s - s0),
                        n_steps - s,
                        seg_steps,
                        x.numel() * x.element_size(),
                        T,
                        x.device,
                    )
            elif seg_steps is not None and x.requires_grad:
                s_end = min(n_steps, s + seg_steps)
                x, ys = torch.utils.checkpoint.checkpoint(
                    segment, x, s, s_end, fail_interval, use_reentrant=False
                )
                s = s_end
            else:
                x, s, ys = step_chunk(x, s, n_steps, fail_interval)
            if buffer is None:
                pieces.append((s, x, ys))
            # "auto": compile for the rest of the run once its predicted eager time (the
            # steps so far, extrapolated) would reach the threshold (checkpointed segments
            # and reruns stay eager)
            if compile == "auto" and fail_interval is None and seg_steps is None and s < n_steps:
                eager_s = time.perf_counter() - tic
                if fast.worth_compiling(eager_s * (n_steps - s_start) / (s - s_start)):
                    x = compile_rest(x, s, eager_s)
        return x, pieces

    def time_major(pieces):
        """The (T, *batch, nx) outputs: x0 and those of the pieces."""
        if buffer is not None:
            return to_state(buffer, 1)
        return torch.cat([x0.unsqueeze(0)] + [ys for _, _, ys in pieces if ys is not None])

    tic = time.perf_counter()
    x, pieces = run(x, 0)
    if compile == "auto" and not fast.active:
        fast.add_eager_seconds(time.perf_counter() - tic, n_steps)
    x_time_major = time_major(pieces)
    messages: list[str] = []
    failed = ~torch.isfinite(to_state(x)).all(-1)  # non-finite states are absorbing
    del x
    if bool(failed.any()):  # the single host synchronisation of the run
        bad = ~torch.isfinite(x_time_major.detach()).all(-1)  # (T, *batch)
        first = bad.to(torch.int8).argmax(0)  # output index of the first bad state
        first = torch.where(failed, first, torch.full_like(first, T))
        if x_time_major.requires_grad:
            # A failed sample's inf/nan would reach the gradient of shared parameters
            # through f's own backward (0 * inf = nan) even where the loss ignores it:
            # rerun from the last piece before the first failure with the failed samples
            # frozen at a finite state from their failing interval on.
            fail_interval = first - 1
            s_fail = int(fail_interval.min()) * m
            pieces = [piece for piece in pieces if piece[0] <= s_fail]
            s_r, x_r = pieces[-1][:2] if pieces else (0, x0)
            x_time_major = None  # release the first run's graph
            pieces += run(x_r, s_r, fail_interval)[1]
            x_time_major = time_major(pieces)
        late = torch.arange(T, device=x0.device) >= first.unsqueeze(-1)  # (*batch, T)
        nan = torch.full_like(x_time_major, float("nan"))
        x_time_major = torch.where(late.movedim(-1, 0).unsqueeze(-1), nan, x_time_major)
        messages = _failure_messages(failed, first, t)
    x_out = x_time_major.movedim(0, -2)  # (*batch, T, nx) view
    status = torch.where(failed, Status.NON_FINITE, Status.SUCCESS).to(torch.int8)
    stats = SolverStats(
        n_f_evals=n_steps * len(scheme.stages),
        n_steps=n_steps,
        extra={
            **fast.stats(),
            "compiled_from_step": compiled_from if fast.active else None,
            "substeps": m,
            "layout": "component-major" if component_major else "interleaved",
            "checkpoint_steps": seg_steps,
        },
    )
    return Solution(t=t, x=x_out, status=status, stats=stats, messages=messages, method=tab.name)


def _failure_messages(failed: torch.Tensor, first: torch.Tensor, t: torch.Tensor) -> list[str]:
    """One message per failed sample: its index and the output interval of the failure."""
    t_host = t.detach().cpu().tolist()
    firsts = first.cpu().numpy()
    msgs = []
    for idx in map(tuple, np.argwhere(failed.cpu().numpy())):
        k = int(firsts[idx])
        sample = idx[0] if len(idx) == 1 else idx
        msgs.append(
            f"sample {sample}: the state became non-finite (inf/nan) between t = "
            f"{t_host[k - 1]:.6g} and t = {t_host[k]:.6g}; its outputs from t = {t_host[k]:.6g} "
            "on are NaN. The solution may escape to infinity in finite time (like x' = x^2, "
            "x(0) = 1 at t = 1, notes eq. 1.44), or the step is too large for stability: try "
            "more substeps, an adaptive method ('dopri5') or an implicit one."
        )
    return msgs
