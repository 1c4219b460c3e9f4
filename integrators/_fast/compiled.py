"""The compiled chunk of a fixed-step explicit run: cache, layout choice and fallbacks.

The solver (``integrators/explicit.py``) builds a chunk function that advances several steps
and asks :func:`compiled_stepper` for a compiled version of it. Compiled chunks are cached per
model (weakly: they go with the model) and configuration, so the one-off compile time is paid
once per model and state shape. A cached chunk reaches the model (and any other callable of
the run) through a :class:`_Slot` filled only while it runs: the cache never holds the model
it is keyed by, so a model that is no longer used is freed with its compiled chunks.
Compilation is given up, and the run continues with the
solver's eager chunks, when ``torch.compile`` fails, when the first call of a compiled chunk
gives other numbers than the eager chunk (a compiler fault: the compiled graph of a model that
takes second derivatives inside ``f`` can silently drop them), or when the compiled graph
cannot be differentiated (a model that calls autograd inside ``f``); the reason is reported.

Every chunk is compiled with the graph passes of ``passes`` (a known inductor fault in
``add``/``sub`` with ``alpha`` is rewritten away); component-wise models
(``cat_forwarding.reads_only_components``) run without autograd get a component-major chunk
whose graph also goes through the cat-forwarding pass (``cat_forwarding``).
"""

from __future__ import annotations

import contextlib
import inspect
import math
import time
import types
import weakref

import torch

#: ``compile="auto"`` compiles a model's chunk (or kernel) for a configuration and state
#: shape once this many seconds were spent, or are predicted to be spent, in its eager runs
#: (over all calls). Rent-or-buy (see :func:`compiled_stepper`): with the threshold near the
#: one-off compile time ``C`` a run sequence costs at most ``1 + C / threshold`` times the
#: better choice made in hindsight, whatever the batch size and the cost of a step. A
#: pendulum RK4 sensitivity kernel compiles in 14-16 s in a fresh process with an empty
#: inductor cache and in 5-10 s with a warm one (docs/benchmarks.md, "Tuning constants").
#: Read at every call: a test may change it.
AUTO_COMPILE_EAGER_SECONDS = 10.0
#: Compiled runs of models with at most this many states keep the state component-major
#: (a (nx, *batch) tensor whose rows the cat-forwarding graph pass lets inductor read straight
#: from the model's own expressions).
COMPONENT_MAJOR_MAX_STATES = 8


def _with_own_code(fn):
    """A copy of the closure ``fn`` with a code object of its own.

    Dynamo keeps compiled graphs per code object and, past ``recompile_limit`` (8) graphs for
    one code object, silently runs it eagerly. Every chunk shares ``chunk``'s code, so without
    a copy the ninth model, configuration or state shape compiled in a process would not be
    compiled.
    """
    code = fn.__code__.replace()
    return types.FunctionType(code, fn.__globals__, fn.__name__, fn.__defaults__, fn.__closure__)


def _backward_works(ys: torch.Tensor, x: torch.Tensor, f) -> bool:
    """Whether the graph of a compiled chunk's outputs ``ys`` can be differentiated with respect
    to the state ``x`` and ``f``'s parameters (one backward, graph kept, no ``.grad`` touched).

    A model that calls autograd inside ``f`` (Lagrangian systems, energy-based networks) builds
    a double-backward graph through the compiled region, which aot_autograd cannot
    differentiate: the error would only surface in the caller's backward. Such a model runs
    eagerly with autograd on (the probe counts as compile time, once per chunk signature).
    """
    params = f.parameters() if isinstance(f, torch.nn.Module) else ()
    inputs = [v for v in (x, *params) if v.requires_grad]
    if not ys.requires_grad or not inputs:
        return True
    try:
        torch.autograd.grad(ys.sum(), inputs, retain_graph=True, allow_unused=True)
    except RuntimeError:
        return False
    return True


def _same_numbers(compiled, eager) -> bool:
    """Whether a compiled chunk's output equals the eager chunk's to rounding: within
    ``sqrt(eps)`` of the largest finite magnitude, NaN where the eager output is NaN."""
    tol = math.sqrt(torch.finfo(eager.dtype).eps)
    scale = float(eager.abs().nan_to_num(0.0, 0.0, 0.0).amax()) if eager.numel() else 0.0
    return torch.allclose(compiled.detach(), eager, rtol=tol, atol=tol * scale, equal_nan=True)


class _Slot:
    """A stand-in for one callable of a run (the model, an input function), called like it.

    The chunks an entry compiles call their callables through slots, which
    :meth:`Stepper.__call__` fills for the duration of a call and empties after it (the last
    of concurrent calls empties it). Dynamo guards on the object a slot holds when a compiled
    chunk is called, as it would on a callable the chunk closed over.
    """

    __slots__ = ("target", "users")

    def __init__(self):
        self.target = None
        self.users = 0

    def __call__(self, *args):
        return self.target(*args)


class _Entry:
    """Compiled chunk functions for one model/configuration, and their usage counters."""

    def __init__(self, n_slots: int):
        self.slots = tuple(_Slot() for _ in range(n_slots))
        # per state shape, dtype and device (each compiles a kernel of its own, so each pays
        # the one-off compile time of "auto" by itself): (wall time, steps) of the eager
        # runs reported by the solver
        self.eager: dict = {}
        self.compiled: dict = {}  # (outputs per chunk, component-major, shape...) -> chunk
        self.reference: dict = {}  # the same key -> the eager chunk the compiled one must match
        self.failed = False
        self.failure = ""  # why the compiled chunk was given up (reported in the stats)
        self.backward_failed = False  # the compiled chunk's graph cannot be differentiated
        self.signatures: set = set()
        # whether the model works component by component (``reads_only_components``), traced
        # once per entry through ``f_at_start`` (the model at the first output time)
        self.componentwise: bool | None = None


_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _cache_entry(f, config, n_slots: int) -> _Entry:
    """The cache entry of model ``f``, its chunks calling ``n_slots`` callables of the run
    through slots. A wrapper that names what it wraps (``__wrapped__``, as ``functools.wraps``
    sets it) is keyed by the wrapped model, a bound method by its instance: dynamo guards on
    what the chunk calls, so a fresh wrapper of the same code and model reuses the compiled
    chunk, and one of another model compiles it again."""
    f = inspect.unwrap(f)
    owner = getattr(f, "__self__", None) if hasattr(f, "__func__") else None
    key_obj = owner if owner is not None else f
    key = (getattr(f, "__func__", None), config)
    try:
        per_model = _CACHE.setdefault(key_obj, {})
    except TypeError:  # not weak-referenceable: nothing is kept between calls
        return _Entry(n_slots)
    return per_model.setdefault(key, _Entry(n_slots))


def clear_compile_cache() -> None:
    """Forget all compiled chunks (the next compiled run compiles again)."""
    _CACHE.clear()


class Stepper:
    """The compiled chunk of one run, or the reason there is none.

    ``n_out``: output intervals per chunk the solver should use (1 where nothing is
    compiled); ``component_major``: whether the compiled chunk takes and returns the state as
    a (nx, *batch) tensor; ``compile_s``: wall time spent compiling during this run.
    """

    def __init__(self, f, callables, entry: _Entry, want, active, key, compile_s, threshold):
        self._f, self._entry, self._want, self._active = f, entry, want, active
        self._callables = callables
        self._state = key[2:]  # the state's shape, dtype and device: the "auto" account
        self._key, self._chunk = key, entry.compiled.get(key)
        self._reference = entry.reference.get(key)
        self._grad_mode = torch.is_grad_enabled()
        self.n_out, self.component_major = (key[0], key[1]) if active else (1, False)
        self.compile_s = compile_s
        self._threshold = threshold  # inf unless compile="auto"

    def add_eager_seconds(self, seconds: float, steps: int = 0) -> None:
        """Count ``seconds`` (and ``steps``) of eager stepping of this model and configuration
        towards ``"auto"`` (see :func:`compiled_stepper`)."""
        spent, done = self._entry.eager.get(self._state, (0.0, 0))
        self._entry.eager[self._state] = (spent + seconds, done + steps)

    def worth_compiling(self, run_eager_s: float) -> bool:
        """Whether an eager ``"auto"`` run predicted to take ``run_eager_s`` seconds in all
        would bring the eager time of this model and configuration to the threshold: the
        caller then compiles for the rest of the run (rent-or-buy with the run's length
        known, see :func:`compiled_stepper`)."""
        if self._active or self._entry.failed:
            return False
        return self._entry.eager.get(self._state, (0.0, 0))[0] + run_eager_s >= self._threshold

    @property
    def active(self) -> bool:
        """Whether calls may run compiled (wanted, and not given up before: for this run's
        grad mode, a compiled graph that cannot be differentiated is given up too)."""
        entry = self._entry
        return self._active and not entry.failed and not (self._grad_mode and entry.backward_failed)

    @contextlib.contextmanager
    def _slots_filled(self):
        """The entry's slots hold this run's callables while the block runs."""
        slots = self._entry.slots
        for slot, target in zip(slots, self._callables, strict=True):
            slot.target, slot.users = target, slot.users + 1
        try:
            yield
        finally:
            for slot in slots:
                slot.users -= 1
                if not slot.users:
                    slot.target = None

    def __call__(self, x: torch.Tensor, *args):
        """The compiled chunk's ``(x_new, outputs)`` for ``chunk(x, *args)``, or None: nothing
        is compiled, or the compiled chunk failed now or before (the caller then runs the
        same chunk eagerly). The first call of each signature counts as compile time and is
        checked against the eager chunk from the same arguments: a compiled chunk that raises
        or gives other numbers (beyond ``sqrt(eps)`` of their magnitude) is given up for this
        model and configuration."""
        entry = self._entry
        if not self.active:
            return None
        signature = (self._key, self._grad_mode, x.requires_grad)
        fresh = signature not in entry.signatures
        try:
            with self._slots_filled():
                if fresh:  # copies: a chunk may write its outputs into a buffer in ``args``
                    devices = [x.device] if x.device.type == "cuda" else []
                    with torch.no_grad(), torch.random.fork_rng(devices):  # the user's stream
                        reference = [y.detach().clone() for y in self._reference(x, *args)]
                tic = time.perf_counter()
                x_new, ys = self._chunk(x, *args)
        except Exception as exc:  # compilation unavailable: fall back to eager, remember it
            entry.failed = True
            entry.failure = f"{type(exc).__name__}: {str(exc).splitlines()[0][:200]}"
            return None
        if fresh and not all(map(_same_numbers, (x_new, ys), reference)):
            entry.failed = True
            entry.failure = (
                "the compiled chunk's result differs from the eager chunk's (the compiler "
                "lost part of f, e.g. second derivatives taken inside f, or f draws random "
                "numbers)"
            )
            return None
        if fresh and self._grad_mode and not _backward_works(ys, x, self._f):
            entry.backward_failed = True
            entry.failure = "the compiled graph cannot be differentiated (autograd in f)"
            return None
        if fresh:
            self.compile_s += time.perf_counter() - tic
            entry.signatures.add(signature)
        return x_new, ys

    def stats(self) -> dict:
        """``compiled`` (every compiled chunk of the run ran compiled), ``compile_fallback``
        (why a requested compiled run went eager, else None) and ``compile_s``."""
        compiled = self.active
        fallback = (self._entry.failure or None) if self._want and not compiled else None
        return {"compiled": compiled, "compile_fallback": fallback, "compile_s": self.compile_s}


def compiled_stepper(
    f,
    config,
    *,
    compile,
    x0: torch.Tensor,
    make_chunk,
    callables: tuple,
    n_out: int,
    f_at_start=None,
    n_steps: int = 0,
) -> Stepper:
    """A compiled chunk function for a run of model ``f``, or the reason there is none.

    Args:
        f: the model, the cache key (bound methods: their instance).
        config: a hashable description of everything else the chunk depends on.
        compile: True, False or ``"auto"``: compile once the eager runs of this model,
            configuration and state shape (dtype, device), over all calls, took
            :data:`AUTO_COMPILE_EAGER_SECONDS` seconds, counting this run's predicted eager
            time (the seconds are reported by the solver through
            :meth:`Stepper.add_eager_seconds`): a run of ``n_steps`` steps is predicted from
            the eager seconds per step counted so far; during a run, the solver compiles
            for the rest of it as soon as the eager time of its first steps, extrapolated,
            reaches the threshold (:meth:`Stepper.worth_compiling`). The rule is
            rent-or-buy: with the threshold at the one-off compile time, the total costs at
            most twice the better of the two choices made in hindsight, whatever the batch
            size. Each state shape compiles a kernel of its own and so keeps an account of
            its own: a model compiled once for a shape runs compiled in every later
            ``"auto"`` run of that shape, and a new shape starts eager.
        x0: (*batch, nx) initial state; the chunk is compiled for its shape, dtype and device.
        make_chunk: ``make_chunk(slots, n_out, component_major)``, the chunk function to
            compile (interleaved (*batch, nx) or component-major (nx, *batch) state), which
            returns a pair of tensors; it must call the run's callables only through
            ``slots``, stand-ins for ``callables`` in the same order (the cached chunk must not
            hold them).
        callables: this run's callables the chunk calls (the model first, or a function of
            the model only: the cache is keyed by ``f`` and ``config``).
        n_out: output intervals per compiled chunk.
        f_at_start: ``x -> f`` at the first output time with the input there, traced once per
            cache entry to decide the layout (runs without autograd, at most
            :data:`COMPONENT_MAJOR_MAX_STATES` states); None: the chunk has one layout, the
            interleaved one.
        n_steps: the steps of this run, for its predicted eager time (0: no prediction).

    Returns:
        A :class:`Stepper`, called like the chunk; it returns None wherever the caller must run
        the chunk eagerly, and reports ``compiled``, ``compile_fallback`` and ``compile_s``.
    """
    entry = _cache_entry(f, config, len(callables))
    state = (tuple(x0.shape), x0.dtype, x0.device)
    threshold = AUTO_COMPILE_EAGER_SECONDS if compile == "auto" else math.inf
    # compiled once for this state: no more eager "auto" runs
    enough = any(key[2:] == state for key in entry.compiled)
    if compile == "auto" and not enough and not entry.failed:
        spent, steps = entry.eager.get(state, (0.0, 0))
        enough = spent + (n_steps * spent / steps if steps else 0.0) >= threshold
    want = compile is True or (compile == "auto" and enough)
    grad_mode = torch.is_grad_enabled()
    active = want and not entry.failed and not torch.compiler.is_compiling()
    active = active and not (grad_mode and entry.backward_failed)
    compile_s = 0.0
    component_major = False
    layouts = f_at_start is not None and x0.shape[-1] <= COMPONENT_MAJOR_MAX_STATES
    if active and not grad_mode and layouts:
        if entry.componentwise is None:  # imports inductor (1 s), traces f: compile time
            tic = time.perf_counter()
            from .cat_forwarding import reads_only_components

            entry.componentwise = reads_only_components(f_at_start, x0.detach())
            compile_s += time.perf_counter() - tic
        component_major = entry.componentwise
    # One compiled function (own code object, see _with_own_code) per chunk length, layout and
    # state shape/dtype/device: dynamo's recompile limit never turns a new shape eager.
    key = (n_out, component_major, *state)
    if active and key not in entry.compiled:
        tic = time.perf_counter()  # the first torch.compile imports dynamo/inductor (seconds)
        from .passes import ChunkGraphPass

        entry.reference[key] = make_chunk(entry.slots, n_out, component_major)
        entry.compiled[key] = torch.compile(
            _with_own_code(entry.reference[key]),
            dynamic=False,
            options={"post_grad_custom_pre_pass": ChunkGraphPass(forward_cats=component_major)},
        )
        compile_s += time.perf_counter() - tic
    return Stepper(f, callables, entry, want, active, key, compile_s, threshold)
