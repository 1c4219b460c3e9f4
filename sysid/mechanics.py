"""Lagrangian mechanics by autograd (notes chapter 2).

:class:`LagrangianSystem` turns a description of a mechanical system (kinetic energy, potential
energy, external forces, holonomic constraints) into the model equations of the notes, with
every derivative taken by autograd and no symbolic inversion:

- kinetic energy from point masses m_i at positions p_i(q) (eq. 2.3-2.6), from distributed
  bodies by Gauss-Legendre quadrature (eq. 2.17-2.20, :func:`distributed_body`), from a
  function T(q, qdot), or a constant diagonal mass matrix (Cartesian coordinates, eq. 2.85,
  2.92); W(q) = d^2 T / d qdot^2 (eq. 2.61);
- potential V(q) (gravity from the point masses, eq. 2.21, plus a user potential; springs with
  rest length via :func:`spring_potential`, eq. 2.31);
- generalised forces Q = sum_i (dp_i/dq)^T F_i of forces F_i acting at points p_i(q)
  (eq. 2.115), plus any direct generalised force (torques, friction);
- constraints c(q) = 0 with multipliers z (Lagrange function eq. 2.125).

Model forms: explicit ODE (eq. 2.42 / 2.131) by a batched linear solve, the implicit ODE
residual (eq. 7.47), the index-3 DAE (eq. 2.126), the index-1 DAE with the KKT matrix
M(q) = [[W, a^T], [a, 0]] (eq. 2.168) and optional Baumgarte stabilisation (eq. 2.186),
consistency conditions (eq. 2.182) and their projection, drift monitors and energy.

Speed: everything is batched reverse-mode autograd on the whole batch at once (samples are
independent, so gradients of batch sums are per-sample gradients), with as few passes as the
structure allows:

- constant diagonal W (Cartesian coordinates): one reverse pass through V;
- point masses: the d'Alembert form W = sum m_i J_i^T J_i, convective term
  sum m_i J_i^T (dJ_i/dt) qdot, from nq + 4 reverse passes through the positions p_i(q) only;
- a general T(q, qdot): one reverse pass gives grad L and W qdot, nq more give W and the
  convective term (d(W qdot)/dq) qdot together.

Public methods localise inputs that carry a long autograd history (see :func:`_local_graph`),
so evaluating the model inside a differentiated simulation costs O(1), not O(steps).

Shapes: q, qdot (*batch, nq); the state of the first-order form is x = [q, qdot]
(*batch, 2 nq); inputs u (*batch, nu); multipliers z (*batch, nc). User callables must accept
arbitrary leading batch dimensions, and samples must not interact.
"""

import contextlib
import math
import threading
import warnings
from collections.abc import Callable, Sequence

import numpy as np
import torch
from torch import nn

from integrators.errors import (
    ConvergenceError,
    InputValidationError,
    RKIdentWarning,
    SingularMatrixError,
)
from integrators.jacobians import gradients
from integrators.newton import minimize


def spring_potential(p_a, p_b, stiffness, rest_length=0.0):
    """Energy 1/2 k (||p_b - p_a|| - L0)^2 of a spring (eq. 2.31; eq. 2.32 when L0 = 0).

    p_a, p_b: (..., D); stiffness, rest_length broadcast against (...,). Returns (...,).
    With a number L0 = 0 the norm is never formed, so the energy is smooth at p_a = p_b; with
    a tensor L0 (a parameter) the norm's derivative is taken as 0 where the points coincide
    (the limit of L0 = 0; for L0 != 0 the force's direction is undefined there), so the
    force stays finite instead of 0 * inf = NaN.
    """
    delta = p_b - p_a
    sq = (delta * delta).sum(-1)
    if isinstance(rest_length, (int, float)) and rest_length == 0:
        return 0.5 * stiffness * sq
    apart = sq > 0
    norm = torch.where(apart, torch.sqrt(torch.where(apart, sq, torch.ones_like(sq))), 0.0)
    return 0.5 * stiffness * (norm - rest_length) ** 2


def _checked_baumgarte(alpha):
    """The Baumgarte gain ``alpha`` (eq. 2.186): None, a finite number >= 0 or a real tensor
    (e.g. (*batch, 1)) of such entries, returned as given (0 is no stabilisation, as None);
    anything else raises InputValidationError (alpha < 0 makes the constraint drift grow
    instead of decay)."""
    if alpha is None:
        return None
    if isinstance(alpha, torch.Tensor):
        ok = alpha.is_floating_point() and bool((torch.isfinite(alpha) & (alpha >= 0)).all())
    else:
        ok = (
            isinstance(alpha, (int, float, np.integer, np.floating))
            and not isinstance(alpha, (bool, np.bool_))
            and math.isfinite(alpha)
            and alpha >= 0
        )
    if not ok:
        raise InputValidationError(
            f"baumgarte must be None or a finite number >= 0 (or a float tensor of them), got "
            f"{alpha!r}: the gain alpha of cddot + 2 alpha cdot + alpha^2 c = 0 (eq. 2.186) "
            "damps the constraint drift for alpha > 0 (0: no stabilisation, as None)."
        )
    return alpha


def distributed_body(mass, position: Callable, n_nodes: int = 4):
    """Point-mass quadrature of a body with uniformly distributed mass (eq. 2.17-2.20, 2.24).

    ``position(q, s)`` gives the material point at body coordinate s in [0, 1] with shape
    (..., D) for q (..., nq) and s broadcast against (...,). Gauss-Legendre with ``n_nodes``
    nodes integrates T and V exactly when ``|pdot(s)|^2`` and p(s) are polynomials of degree
    <= 2 n_nodes - 1 in s (a straight rod needs 2 nodes).

    Returns (masses (n_nodes,), positions(q) -> (..., n_nodes, D)) to be combined with the
    other point masses of a LagrangianSystem.
    """
    nodes, weights = np.polynomial.legendre.leggauss(n_nodes)
    s = torch.as_tensor((nodes + 1) / 2, dtype=torch.float64)
    w = torch.as_tensor(weights / 2, dtype=torch.float64)
    masses = mass * w.to(mass.dtype if isinstance(mass, torch.Tensor) else torch.float64)

    def positions(q):
        return torch.stack([position(q, float(sk)) for sk in s], dim=-2)

    return masses, positions


class _AttachInputs(torch.autograd.Function):
    """Zeros whose vector-Jacobian product is that of ``local_outputs`` w.r.t. ``local_inputs``.

    Adding it to outputs computed from detached leaf copies of inputs that carry a long
    history (e.g. a state inside a simulation being differentiated) reconnects them to that
    history, while the many local reverse passes of the Lagrange terms only traverse the small
    local graph (the autograd engine visits every node reachable from the root, so working on
    the original inputs would make each evaluation cost O(length of the simulation)).
    """

    @staticmethod
    def forward(ctx, n_in, *tensors):
        ctx.n_in = n_in
        ctx.local_in = tensors[n_in : 2 * n_in]
        ctx.local_out = tensors[2 * n_in :]
        return tuple(torch.zeros_like(t) for t in ctx.local_out)

    @staticmethod
    def backward(ctx, *grad_out):
        # an output that does not depend on the inputs (e.g. the curvature term of quadratic
        # constraints when only the multipliers carry a history) contributes nothing
        used = [i for i, out in enumerate(ctx.local_out) if out.requires_grad]
        grads = (None,) * len(ctx.local_in)
        if used:
            grads = torch.autograd.grad(
                [ctx.local_out[i] for i in used],
                ctx.local_in,
                [grad_out[i] for i in used],
                retain_graph=True,
                create_graph=torch.is_grad_enabled(),
                allow_unused=True,
            )
        return (None, *grads, *([None] * (len(ctx.local_in) + len(ctx.local_out))))


_STATE = threading.local()


def _local_graph(method):
    """Public entry points run on detached leaf copies of the tensor arguments that carry a
    history (reconnected by :class:`_AttachInputs`); without grad mode on detached copies.

    Only the outermost call localises (nested calls see the local leaves and build ordinary
    graphs), so all derivatives inside one call are exact to any order. Across the boundary the
    reconnection is first order in those arguments: gradients w.r.t. them and w.r.t. the
    parameters are exact, second derivatives w.r.t. a state with history are not propagated.
    """

    def wrapper(self, *args, **kwargs):
        if getattr(_STATE, "depth", 0) > 0:
            return method(self, *args, **kwargs)
        if not torch.is_grad_enabled():
            local = [a.detach() if isinstance(a, torch.Tensor) else a for a in args]
            return _nested(method, self, local, kwargs)
        idx = [
            i for i, a in enumerate(args) if isinstance(a, torch.Tensor) and a.grad_fn is not None
        ]
        if not idx:
            return _nested(method, self, args, kwargs)
        local = list(args)
        for i in idx:
            local[i] = args[i].detach().requires_grad_(True)
        out = _nested(method, self, local, kwargs)
        single = isinstance(out, torch.Tensor)
        outs = (out,) if single else tuple(out)
        zeros = _AttachInputs.apply(
            len(idx), *[args[i] for i in idx], *[local[i] for i in idx], *outs
        )
        joined = tuple(o + z for o, z in zip(outs, zeros, strict=True))
        return joined[0] if single else joined

    wrapper.__name__, wrapper.__doc__ = method.__name__, method.__doc__
    return wrapper


@contextlib.contextmanager
def exact_higher_derivatives():
    """Within this context, public methods of LagrangianSystem do not localise their inputs,
    so derivatives of any order w.r.t. states with a history are exact (used by the DAE tools,
    which differentiate the model equations several times at a point)."""
    _STATE.depth = getattr(_STATE, "depth", 0) + 1
    try:
        yield
    finally:
        _STATE.depth -= 1


def _nested(method, self, args, kwargs):
    _STATE.depth = getattr(_STATE, "depth", 0) + 1
    try:
        # the tensors this call's graph saves stay with it, whatever saved-tensor hooks are
        # active outside: the derivatives taken inside the call read them at once, and under
        # torch.utils.checkpoint (odeint(..., checkpoint=True)) each such read would recompute
        # the checkpointed segment so far, a cost that grows with the square of its length
        with torch.autograd.graph.saved_tensors_hooks(_keep, _keep):
            return method(self, *args, **kwargs)
    finally:
        _STATE.depth -= 1


def _keep(tensor: torch.Tensor) -> torch.Tensor:
    return tensor


def _wider_batch(value: torch.Tensor, *states: torch.Tensor):
    """The batch of the per-member quantity ``value`` (*batch,) and the ``states`` (*b, n)
    where some state's batch is narrower (parameters or inputs batch the members beyond it),
    else None. A gradient with respect to a state shared by several members would sum their
    terms: the callers expand the states to that batch and evaluate again."""
    batch = torch.broadcast_shapes(value.shape, *(x.shape[:-1] for x in states))
    return batch if any(x.shape[:-1] != batch for x in states) else None


def _solve(matrix: torch.Tensor, rhs: torch.Tensor, what: str, strict: bool = False):
    """Batched solve of matrix @ sol = rhs: matrix (*batch, n, n), rhs (*batch, n) (broadcast).

    A batch member whose (finite) matrix is exactly singular gets a NaN solution and an
    :class:`RKIdentWarning` names it (``strict``: a :class:`SingularMatrixError` instead), so
    one bad member of a batched simulation does not stop the others: the integrators report
    it as NON_FINITE. A member with a non-finite matrix (a state that already diverged) gets
    NaN without a warning. Singular members are solved with the identity instead, so that
    their (masked) gradients stay zero rather than NaN.
    """
    sol, info = torch.linalg.solve_ex(matrix, rhs.unsqueeze(-1))
    sol = sol.squeeze(-1)
    failed = info != 0
    if not bool(failed.any()):  # one host synchronisation per solve
        return sol
    singular = failed & torch.isfinite(matrix).all(-1).all(-1)
    if bool(singular.any()):
        idx = [i[0] if len(i) == 1 else tuple(i) for i in torch.nonzero(singular)[:5].tolist()]
        message = (
            f"{what} is singular at batch index {idx}"
            f"{' (and more)' if int(singular.sum()) > 5 else ''}; "
        )
        if strict:
            raise SingularMatrixError(
                message + "check the configuration (e.g. a degenerate constraint gradient or a "
                "zero mass) or project the initial conditions"
            )
        warnings.warn(
            message + "its accelerations are NaN (an integrator reports it as NON_FINITE). "
            "Check the configuration there (a coordinate singularity, a zero mass or lever "
            "arm, dependent constraint gradients).",
            RKIdentWarning,
            stacklevel=2,
        )
    eye = torch.eye(matrix.shape[-1], dtype=matrix.dtype, device=matrix.device)
    safe = torch.where(failed[..., None, None], eye, matrix)
    sol = torch.linalg.solve(safe, rhs.unsqueeze(-1)).squeeze(-1)
    return torch.where(failed.unsqueeze(-1), torch.full_like(sol, float("nan")), sol)


def _check_masses(masses, name: str, n: int | None = None) -> None:
    """Raise InputValidationError unless masses given as numbers are finite and > 0 (a zero
    or negative mass makes W(q) singular or indefinite), and, for ``n``, of shape (n,).
    Callables (masses that are parameters changing during a fit) are not checked here."""
    if masses is None or callable(masses):
        return
    values = torch.as_tensor(masses.detach() if isinstance(masses, torch.Tensor) else masses)
    if n is not None and values.shape not in ((), (n,)):
        raise InputValidationError(
            f"{name} must be a scalar or have shape ({n},) (one per coordinate), got "
            f"{tuple(values.shape)}"
        )
    bad = ~(torch.isfinite(values) & (values > 0))
    if bool(bad.any()):
        idx = torch.nonzero(bad.reshape(-1))[:5].reshape(-1).tolist()
        raise InputValidationError(
            f"{name} must be finite and > 0, got {values.reshape(-1)[idx].tolist()} at "
            f"index {idx}; a zero or negative mass makes the mass matrix W(q) singular or "
            "indefinite"
        )


class LagrangianSystem(nn.Module):
    """A mechanical system in generalised coordinates q (notes chapter 2).

    Give the kinetic energy in one of three ways (subclasses may instead override the hook
    methods of the same names):

    - ``diagonal_mass``: tensor (nq,) (or a scalar) or callable () -> (nq,):
      T = 1/2 sum_k w_k qdot_k^2 with a constant diagonal W (Cartesian coordinates, eq. 2.85,
      2.92); fastest path;
    - ``point_masses`` (n_p,) and ``positions(q) -> (*batch, n_p, D)``:
      ``T = 1/2 sum m_i |pdot_i|^2`` (eq. 2.3), pdot_i = J_i qdot by autograd (eq. 2.4);
    - ``kinetic_energy(q, qdot) -> (*batch,)``: any T, quadratic in qdot (eq. 2.7).

    Further arguments: ``potential(q) -> (*batch,)``; ``gravity`` (D,) field acceleration,
    e.g. (0, -9.81) with the vertical axis up, giving V = -sum m_i g . p_i (eq. 2.21, needs
    point masses); ``generalized_force(q, qdot, u) -> (*batch, nq)``; forces at points:
    ``force_points(q) -> (*batch, n_f, D)`` with ``point_forces(q, qdot, u) -> (*batch, n_f,
    D)`` (eq. 2.115); ``constraints(q) -> (*batch, nc)``; ``baumgarte`` alpha >= 0 (eq. 2.186)
    used by the index-1 forms unless overridden per call (a float, or a tensor (*batch, 1)
    broadcasting against the batch, e.g. several stabilisation gains in one simulation).

    ``forward(t, x, u=None)`` is the explicit first-order ODE xdot = [qdot, qddot] (the KKT
    index-1 form for a constrained system), usable directly as ``f`` in ``odeint``.

    The state is x = [q, qdot], ``nx = 2 nq`` entries named by ``state_names``: the
    ``coordinate_names`` (nq strings, default ``q1..qn``) followed by the same names with
    ``dot`` appended (``q1dot..qndot``).

    Masses given as numbers or tensors must be finite and > 0 (InputValidationError at
    construction). Masses from callables or overridden hooks (parameters that change during a
    fit) are not checked per call: where W(q) or the KKT matrix is singular for a batch member,
    its accelerations are NaN and an :class:`RKIdentWarning` names it (a zero entry of a
    diagonal W divides by zero instead, without a warning); the integrators report such members
    as NON_FINITE. Positions, constraints, energies and force points may be affine in q, or
    independent of some coordinates: the missing derivatives are zero.

    Gradients reach the state, the module's parameters (an ``nn.Module`` passed as a callable
    is registered as a submodule) and mass / gravity tensors returned by the hooks; tensors
    captured in closures of the other callables are not seen, so results are detached from
    them unless one of the former requires grad: register such tensors on the module.
    """

    def __init__(
        self,
        nq: int,
        *,
        nu: int = 0,
        diagonal_mass=None,
        point_masses=None,
        positions: Callable | None = None,
        kinetic_energy: Callable | None = None,
        potential: Callable | None = None,
        gravity=None,
        generalized_force: Callable | None = None,
        force_points: Callable | None = None,
        point_forces: Callable | None = None,
        constraints: Callable | None = None,
        baumgarte: float | None = None,
        coordinate_names: Sequence[str] | None = None,
    ):
        super().__init__()
        self.nq = int(nq)
        self.nu = int(nu)
        if coordinate_names is None:
            coordinate_names = [f"q{i + 1}" for i in range(self.nq)]
        self.coordinate_names = tuple(str(n) for n in coordinate_names)
        self._diagonal_mass = diagonal_mass
        self._point_masses = point_masses
        self._positions = positions
        self._kinetic = kinetic_energy
        self._potential = potential
        self._gravity = gravity
        self._generalized_force = generalized_force
        self._force_points = force_points
        self._point_forces = point_forces
        self._constraints = constraints
        self.baumgarte = _checked_baumgarte(baumgarte)
        if (force_points is None) != (point_forces is None):
            raise InputValidationError("give both force_points and point_forces, or neither")
        if self.nq < 1 or self.nu < 0:
            raise InputValidationError(f"need nq >= 1 and nu >= 0, got nq={nq}, nu={nu}")
        if len(self.coordinate_names) != self.nq:
            raise InputValidationError(
                f"coordinate_names has {len(self.coordinate_names)} entries; need nq = {self.nq}"
            )
        _check_masses(diagonal_mass, "diagonal_mass", self.nq)
        _check_masses(point_masses, "point_masses")
        if point_masses is not None and positions is None and kinetic_energy is None:
            raise InputValidationError("point_masses need positions(q) -> (*batch, n_p, D)")

    @property
    def nx(self) -> int:
        """Width of the state x = [q, qdot], ``2 nq``."""
        return 2 * self.nq

    @property
    def state_names(self) -> tuple[str, ...]:
        """Names of the entries of x = [q, qdot]: the coordinates, then their rates ``...dot``."""
        return self.coordinate_names + tuple(f"{n}dot" for n in self.coordinate_names)

    # ------------------------------------------------------------------ hooks (overridable)
    def diagonal_mass(self):
        """Constant diagonal of W, (nq,), or None (then W depends on q)."""
        m = self._diagonal_mass
        return m() if callable(m) else m

    def point_masses(self):
        """Masses of the point masses, (n_p,), or None."""
        m = self._point_masses
        return m() if callable(m) else m

    def positions(self, q):
        """Positions of the point masses, (*batch, n_p, D), or None."""
        return None if self._positions is None else self._positions(q)

    def gravity(self):
        """Field acceleration vector (D,) acting on the point masses, or None."""
        g = self._gravity
        return g() if callable(g) else g

    def potential(self, q):
        """User potential V(q), (*batch,), or None (gravity of point masses is added apart)."""
        return None if self._potential is None else self._potential(q)

    def generalized_force(self, q, qdot, u):
        """Direct generalised force (*batch, nq) or None."""
        return None if self._generalized_force is None else self._generalized_force(q, qdot, u)

    def force_points(self, q):
        """Points (*batch, n_f, D) where the forces of ``point_forces`` act, or None."""
        return None if self._force_points is None else self._force_points(q)

    def point_forces(self, q, qdot, u):
        """Forces (*batch, n_f, D) acting at ``force_points(q)``, or None."""
        return None if self._point_forces is None else self._point_forces(q, qdot, u)

    def constraints(self, q):
        """Holonomic constraints c(q), (*batch, nc), or None."""
        return None if self._constraints is None else self._constraints(q)

    # ------------------------------------------------------------------ argument checks
    def _split_state(self, x, where: str):
        """(q, qdot) of a state x = [q, qdot] (*batch, 2 nq); InputValidationError otherwise."""
        n = 2 * self.nq
        if not isinstance(x, torch.Tensor) or x.dim() < 1 or x.shape[-1] != n:
            got = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
            raise InputValidationError(
                f"{type(self).__name__}.{where}: the state x = [q, qdot] must have shape "
                f"(*batch, 2 nq) = (*batch, {n}), got {got}"
            )
        return x[..., : self.nq], x[..., self.nq :]

    def _check_args(self, where: str, u=None, **coordinates) -> None:
        """InputValidationError unless every given coordinate tensor is (*batch, nq) and the
        input u is (*batch, nu) (u is checked only when the system declares nu > 0)."""
        for name, value in coordinates.items():
            if value is not None and (value.dim() < 1 or value.shape[-1] != self.nq):
                raise InputValidationError(
                    f"{type(self).__name__}.{where}: {name} must have shape (*batch, nq) = "
                    f"(*batch, {self.nq}), got {tuple(value.shape)}"
                )
        if self.nu > 0 and isinstance(u, torch.Tensor) and (u.dim() < 1 or u.shape[-1] != self.nu):
            raise InputValidationError(
                f"{type(self).__name__}.{where}: the input u must have shape (*batch, nu) = "
                f"(*batch, {self.nu}), got {tuple(u.shape)}"
            )

    # ------------------------------------------------------------------ energies
    def _cast(self, value, like):
        return torch.as_tensor(value, dtype=like.dtype, device=like.device)

    def _masses_of(self, points, q):
        """The point masses (n_p,) or per batch member (*batch, n_p) in q's dtype, checked
        against points (*batch, n_p, D)."""
        masses = self._cast(self.point_masses(), q)
        if masses.shape[-1:] != points.shape[-2:-1]:
            raise InputValidationError(
                f"{type(self).__name__}: point_masses has shape {tuple(masses.shape)} but "
                f"positions(q) gives {points.shape[-2]} points (shape (*batch, n_p, D) = "
                f"{tuple(points.shape)}); give one mass per point"
            )
        return masses

    @property
    def is_constrained(self) -> bool:
        """Whether the system has holonomic constraints (``constraints`` given or the hook
        overridden and not returning None)."""
        return self._constrained_at(None)

    def _constrained_at(self, q) -> bool:
        """:attr:`is_constrained`, evaluating an overridden hook at q (None: at q = 0 in the
        dtype and device of the module's parameters, float64 on the CPU without any)."""
        if type(self).constraints is LagrangianSystem.constraints:
            return self._constraints is not None
        if q is None:
            like = next(self.parameters(), torch.zeros((), dtype=torch.float64))
            q = torch.zeros(1, self.nq, dtype=like.dtype, device=like.device)
        return self.constraints(q) is not None

    @_local_graph
    def kinetic_energy(self, q, qdot):
        """T(q, qdot), (*batch,) (eq. 2.3 / 2.7)."""
        if self._kinetic is not None:
            return self._kinetic(q, qdot)
        w = self.diagonal_mass()
        if w is not None:
            return 0.5 * (self._cast(w, q) * qdot * qdot).sum(-1)
        masses = self.point_masses()
        if masses is None:
            raise InputValidationError(
                "LagrangianSystem needs diagonal_mass, point_masses with positions, or "
                "kinetic_energy"
            )
        pdot = self.point_velocities(q, qdot)
        return 0.5 * (self._masses_of(pdot, q) * (pdot * pdot).sum(-1)).sum(-1)

    @_local_graph
    def point_velocities(self, q, qdot):
        """pdot_i = (dp_i/dq) qdot (eq. 2.4), (*batch, n_p, D), by two reverse passes (the
        Jacobian-vector product as the derivative of a vector-Jacobian product), which keeps
        the whole computation in plain batched autograd."""
        with torch.enable_grad():
            qq = self._leaf(q)
            p = self.positions(qq)
            probe = torch.zeros_like(p, requires_grad=True)
            jt_probe = gradients(p, qq, probe, create_graph=True)
            pdot = gradients(jt_probe, probe, qdot, create_graph=True)
        return pdot

    @_local_graph
    def potential_energy(self, q):
        """V(q) = user potential + gravity of the point masses (eq. 2.21), (*batch,)."""
        v = self.potential(q)
        v = torch.zeros(q.shape[:-1], dtype=q.dtype, device=q.device) if v is None else v
        g = self.gravity()
        if g is not None:
            masses, p = self.point_masses(), self.positions(q)
            if masses is None or p is None:
                raise InputValidationError("gravity needs point_masses and positions")
            height = (p * self._cast(g, q).unsqueeze(-2)).sum(-1)  # g . p_i, g (D,) or (*batch, D)
            v = v - (self._masses_of(p, q) * height).sum(-1)
        return v

    @_local_graph
    def energy(self, q, qdot):
        """Total energy T + V, (*batch,); conserved by unforced, undamped systems."""
        self._check_args("energy", q=q, qdot=qdot)
        return self.kinetic_energy(q, qdot) + self.potential_energy(q)

    def lagrangian(self, q, qdot):
        """L = T - V (eq. 2.33), (*batch,)."""
        return self.kinetic_energy(q, qdot) - self.potential_energy(q)

    # ------------------------------------------------------------------ Lagrange equation terms
    @_local_graph
    def generalized_forces(self, q, qdot, u=None):
        """Q = generalized_force + sum_i (dp_i/dq)^T F_i (eq. 2.115), (*batch, nq); None when
        the system has no external forces."""
        total = self.generalized_force(q, qdot, u)
        forces = self.point_forces(q, qdot, u)
        if forces is not None:
            create = self._needs_graph(q, qdot, forces)
            # forces may broadcast against q (an input shared by the batch, or per-sample
            # inputs for one state): J^T F per sample of the broadcast batch
            batch = torch.broadcast_shapes(q.shape[:-1], forces.shape[:-2])
            with torch.enable_grad():
                qq = self._leaf(q.expand(*batch, q.shape[-1]))
                points = self.force_points(qq)
                wider = _wider_batch(points[..., 0, 0], qq)  # parameters batch the points
                if wider is not None:
                    qq = self._leaf(q.expand(*wider, q.shape[-1]).contiguous())
                    points = self.force_points(qq)
                q_force = gradients(
                    points, qq, forces.expand_as(points), create_graph=create
                )  # per-sample J^T F: the points of different samples are independent
            q_force = q_force if create else q_force.detach()
            total = q_force if total is None else total + q_force
        return total

    def _needs_graph(self, *tensors) -> bool:
        """Whether results must stay differentiable: grad mode is on and an argument, a
        parameter of the module or a mass / gravity tensor given by the hooks requires grad.
        Tensors captured by other user callables are not seen: register them on the module
        (an ``nn.Module`` callable is a submodule; or subclass with ``nn.Parameter``s)."""
        if not torch.is_grad_enabled():
            return False
        if any(t.requires_grad for t in tensors):
            return True
        if any(p.requires_grad for p in self.parameters()):
            return True
        hooks = (self.diagonal_mass(), self.point_masses(), self.gravity())
        return any(isinstance(h, torch.Tensor) and h.requires_grad for h in hooks)

    @staticmethod
    def _leaf(x):
        return x if x.requires_grad else x.detach().requires_grad_(True)

    def _terms_general(self, q, qdot):
        """grad_q L, W and (d(W qdot)/dq) qdot (eq. 2.40) by batched reverse-mode autograd.

        One reverse pass gives (grad_q L, grad_qdot L = W qdot) for the whole batch (samples
        are independent, so the gradient of the summed Lagrangian is per-sample); nq further
        reverse passes through grad_qdot L give the rows of W (d/dqdot) and of d(W qdot)/dq,
        contracted with qdot on the fly.
        """
        n = self.nq
        create = self._needs_graph(q, qdot)
        with torch.enable_grad():
            qq, qdd = self._leaf(q), self._leaf(qdot)
            lag = self.lagrangian(qq, qdd)
            batch = _wider_batch(lag, qq, qdd)
            if batch is not None:
                qq, qdd = (self._leaf(x.expand(*batch, n).contiguous()) for x in (q, qdot))
                lag = self.lagrangian(qq, qdd)
            grad_l, momentum = gradients(lag.sum(), (qq, qdd), create_graph=True)
            rows, convective = [], []
            for j in range(n):
                d_q, d_qd = gradients(momentum[..., j].sum(), (qq, qdd), create_graph=create)
                rows.append(d_qd)
                convective.append((d_q * qdot).sum(-1))
        mass, convective = torch.stack(rows, -2), torch.stack(convective, -1)
        if not create:
            return grad_l.detach(), mass.detach(), convective.detach()
        return grad_l, mass, convective

    def _uses_point_masses(self) -> bool:
        return (
            self._kinetic is None
            and type(self).kinetic_energy is LagrangianSystem.kinetic_energy
            and self.diagonal_mass() is None
            and self.point_masses() is not None
        )

    def _terms_points(self, q, qdot):
        """W and grad_q T - (d(W qdot)/dq) qdot for point masses, d'Alembert form (eq. 2.5-2.6):
        W = sum_i m_i J_i^T J_i and the convective term sum_i m_i J_i^T (dJ_i/dt qdot), with
        the Jacobians J_i = dp_i/dq (nq directional derivatives) and the second directional
        derivatives of p_i along qdot, all by reverse passes through the positions only."""
        n = self.nq
        create = self._needs_graph(q, qdot)
        with torch.enable_grad():
            qq = self._leaf(q)
            p = self.positions(qq)
            batch = _wider_batch(p[..., 0, 0], qq, qdot)
            if batch is not None:
                q, qdot = (x.expand(*batch, n).contiguous() for x in (q, qdot))
                qq = self._leaf(q)
                p = self.positions(qq)
            flat = p.reshape(*p.shape[:-2], -1)
            probe = torch.zeros_like(flat, requires_grad=True)
            jt_probe = gradients(flat, qq, probe, create_graph=True)
            eye = torch.eye(n, dtype=q.dtype, device=q.device)
            columns = [
                gradients(jt_probe, probe, eye[j].expand_as(q), create_graph=create)
                for j in range(n)
            ]
            pdot = gradients(jt_probe, probe, qdot, create_graph=True)
            probe2 = torch.zeros_like(pdot, requires_grad=True)
            jt2 = gradients(pdot, qq, probe2, create_graph=True)
            accel = gradients(jt2, probe2, qdot, create_graph=create)
        jac = torch.stack(columns, -1)  # (*batch, n_p * D, nq)
        masses = self._masses_of(p, q)
        dim = p.shape[-1]
        weights = masses.repeat_interleave(dim, dim=-1)  # per coordinate of flat
        mass = jac.transpose(-1, -2) @ (weights.unsqueeze(-1) * jac)
        convective = (jac.transpose(-1, -2) @ (weights * accel).unsqueeze(-1)).squeeze(-1)
        if not create:
            mass, convective = mass.detach(), convective.detach()
        return mass, -convective

    def _grad_potential(self, q):
        """grad V by one reverse pass on the batch (V of different samples are independent)."""
        create = self._needs_graph(q)
        with torch.enable_grad():
            qq = self._leaf(q)
            v = self.potential_energy(qq)
            batch = _wider_batch(v, qq)
            if batch is not None:
                qq = self._leaf(q.expand(*batch, q.shape[-1]).contiguous())
                v = self.potential_energy(qq)
            g = gradients(v, qq, torch.ones_like(v), create_graph=create)
        return g if create else g.detach()

    @_local_graph
    def mass_matrix(self, q, qdot=None):
        """W(q) = d^2 T / d qdot^2 (eq. 2.61), (*batch, nq, nq)."""
        self._check_args("mass_matrix", q=q, qdot=qdot)
        w = self.diagonal_mass()
        if w is not None:
            return torch.diag_embed(self._cast(w, q).expand(q.shape))
        qdot = torch.zeros_like(q) if qdot is None else qdot
        if self._uses_point_masses():
            return self._terms_points(q, qdot)[0]
        return self._terms_general(q, qdot)[1]

    @_local_graph
    def lagrange_terms(self, q, qdot, u=None):
        """(W, r) with W qddot = r the unconstrained Lagrange equation (eq. 2.40 with Q, 2.112):
        r = Q + grad_q L - (d(W qdot)/dq) qdot. W is (*batch, nq) (its diagonal) when the mass
        matrix is constant and diagonal, else (*batch, nq, nq)."""
        self._check_args("lagrange_terms", u, q=q, qdot=qdot)
        force = self.generalized_forces(q, qdot, u)
        w = self.diagonal_mass()
        if w is not None:
            mass, rhs = self._cast(w, q), -self._grad_potential(q)
        elif self._uses_point_masses():
            mass, rhs = self._terms_points(q, qdot)
            rhs = rhs - self._grad_potential(q)
        else:
            grad_l, mass, convective = self._terms_general(q, qdot)
            rhs = grad_l - convective
        rhs = rhs if force is None else rhs + force
        # one batch for both (the shape tells a diagonal W from a full one): inputs or
        # parameters may batch r beyond W, or W beyond r
        n, diagonal = self.nq, w is not None
        batch = torch.broadcast_shapes(
            q.shape[:-1], rhs.shape[:-1], mass.shape[:-1] if diagonal else mass.shape[:-2]
        )
        mass = mass.expand(*batch, n) if diagonal else mass.expand(*batch, n, n)
        return mass, rhs.expand(*batch, n)

    @_local_graph
    def accelerations(self, q, qdot, u=None):
        """qddot of the unconstrained system by a batched linear solve (eq. 2.42)."""
        mass, rhs = self.lagrange_terms(q, qdot, u)
        if mass.dim() == rhs.dim():
            return rhs / mass
        return _solve(mass, rhs, "the mass matrix W(q)")

    # ------------------------------------------------------------------ constraints
    @_local_graph
    def constraint_terms(self, q, qdot):
        """(c, a, cdot, curvature): c (*batch, nc), a = dc/dq (*batch, nc, nq), cdot = a qdot
        (eq. 2.165a), curvature = (d(a qdot)/dq) qdot (eq. 2.165b); 2 nc reverse passes."""
        self._check_args("constraint_terms", q=q, qdot=qdot)
        create = self._needs_graph(q, qdot)
        with torch.enable_grad():
            qq = self._leaf(q)
            c = self.constraints(qq)
            batch = _wider_batch(c.sum(-1), qq, qdot)
            if batch is not None:
                q, qdot = (x.expand(*batch, x.shape[-1]).contiguous() for x in (q, qdot))
                qq = self._leaf(q)
                c = self.constraints(qq)
            rows, curvature = [], []
            for i in range(c.shape[-1]):
                a_i = gradients(c[..., i].sum(), qq, create_graph=True)
                cdot_i = (a_i * qdot).sum(-1)
                d_q = gradients(cdot_i.sum(), qq, create_graph=create)
                rows.append(a_i)
                curvature.append((d_q * qdot).sum(-1))
            a = torch.stack(rows, -2)
            curvature = torch.stack(curvature, -1)
        cdot = (a @ qdot.unsqueeze(-1)).squeeze(-1)
        if not create:
            return c.detach(), a.detach(), cdot.detach(), curvature.detach()
        return c, a, cdot, curvature

    @_local_graph
    def consistency(self, q, qdot):
        """C(q, qdot) = [c(q); cdot(q, qdot)] (eq. 2.182), (*batch, 2 nc)."""
        c, _, cdot, _ = self.constraint_terms(q, qdot)
        return torch.cat([c, cdot], -1)

    @_local_graph
    def drift(self, x):
        """Drift monitors (c(q(t)), cdot(t)) along states x (*batch, T, 2 nq) or (*batch, 2 nq)."""
        q, qdot = self._split_state(x, "drift")
        c, _, cdot, _ = self.constraint_terms(q, qdot)
        return c, cdot

    @_local_graph
    def kkt_matrix(self, q):
        """M(q) = [[W, a^T], [a, 0]] (eq. 2.168), (*batch, nq + nc, nq + nc)."""
        qdot = torch.zeros_like(q)
        mass = self.mass_matrix(q, qdot)
        _, a, _, _ = self.constraint_terms(q, qdot)
        nc = a.shape[-2]
        top = torch.cat([mass, a.transpose(-1, -2)], -1)
        bottom = torch.cat([a, a.new_zeros(*a.shape[:-2], nc, nc)], -1)
        return torch.cat([top, bottom], -2)

    @_local_graph
    def kkt_solve(self, q, qdot, u=None, baumgarte: float | None = None):
        """(qddot, z) of the index-1 form (eq. 2.168) with cddot + 2 alpha cdot + alpha^2 c = 0
        (eq. 2.186) when alpha = ``baumgarte`` (default ``self.baumgarte``; None: cddot = 0)."""
        alpha = self.baumgarte if baumgarte is None else _checked_baumgarte(baumgarte)
        mass, rhs = self.lagrange_terms(q, qdot, u)
        c, a, cdot, curv = self.constraint_terms(q, qdot)
        b = -curv
        if alpha is not None:
            b = b - 2 * alpha * cdot - alpha**2 * c
        if mass.dim() == rhs.dim():  # diagonal W: Schur complement on the multipliers
            a_winv = a / mass.unsqueeze(-2)
            schur = a_winv @ a.transpose(-1, -2)
            z = _solve(
                schur,
                (a_winv @ rhs.unsqueeze(-1)).squeeze(-1) - b,
                "a W^-1 a^T (dependent or zero constraint gradients a(q))",
            )
            qddot = (rhs - (a.transpose(-1, -2) @ z.unsqueeze(-1)).squeeze(-1)) / mass
            return qddot, z
        nc = a.shape[-2]
        top = torch.cat([mass, a.transpose(-1, -2)], -1)
        bottom = torch.cat([a, a.new_zeros(*a.shape[:-2], nc, nc)], -1)
        sol = _solve(torch.cat([top, bottom], -2), torch.cat([rhs, b], -1), "the KKT matrix M(q)")
        return sol[..., : self.nq], sol[..., self.nq :]

    # ------------------------------------------------------------------ model forms
    @_local_graph
    def forward(self, t, x, u=None):
        """Explicit first-order ODE xdot = [qdot, qddot], x = [q, qdot] (*batch, 2 nq).

        A batch member where W(q) (or the KKT matrix) is singular gets NaN accelerations and
        an :class:`RKIdentWarning` names it; the integrators then report it as NON_FINITE and
        integrate the other members on. InputValidationError for a state whose last
        dimension is not 2 nq or an input whose last dimension is not nu.
        """
        q, qdot = self._split_state(x, "forward")
        self._check_args("forward", u)
        if self._constrained_at(q):
            qddot, _ = self.kkt_solve(q, qdot, u)
        else:
            qddot = self.accelerations(q, qdot, u)
        return torch.cat([qdot.expand_as(qddot), qddot], -1)  # inputs may batch qddot

    @_local_graph
    def implicit_residual(self, t, xdot, x, u=None):
        """F(t, xdot, x, u) of eq. (7.47): [qdot' - v; W(q) v' - r(q, v, u)] (unconstrained)."""
        q, v = self._split_state(x, "implicit_residual")
        self._split_state(xdot, "implicit_residual")
        mass, rhs = self.lagrange_terms(q, v, u)
        vdot = xdot[..., self.nq :]
        wv = mass * vdot if mass.dim() == rhs.dim() else (mass @ vdot.unsqueeze(-1)).squeeze(-1)
        return torch.cat([xdot[..., : self.nq] - v, wv - rhs], -1)

    @_local_graph
    def _dynamics_with_multipliers(self, x, z, u=None):
        """xdot = [v, W^-1 (r - a^T z)] (eq. 2.126) for multipliers z (*batch, nc), and the
        constraint terms (c, a, cdot, curvature) of :meth:`constraint_terms` it used."""
        q, v = self._split_state(x, "index3_dae/index1_dae f")
        mass, rhs = self.lagrange_terms(q, v, u)
        diagonal = mass.dim() == rhs.dim()  # (z may batch rhs further)
        terms = self.constraint_terms(q, v)
        rhs = rhs - (terms[1].transpose(-1, -2) @ z.unsqueeze(-1)).squeeze(-1)
        vdot = rhs / mass if diagonal else _solve(mass, rhs, "W(q)")
        return torch.cat([v.expand_as(vdot), vdot], -1), *terms

    def _f_with_multipliers(self, t, x, z, u=None):
        return self._dynamics_with_multipliers(x, z, u)[0]

    def index3_dae(self):
        """Semi-explicit index-3 DAE (eq. 2.126): returns (f, g) with xdot = f(t, x, z, u) =
        [v, W^-1 (r - a^T z)] and 0 = g(t, x, z, u) = c(q)."""

        def g(t, x, z, u=None):
            return self.constraints(x[..., : self.nq])

        return self._f_with_multipliers, g

    def index1_dae(self, baumgarte: float | None = None):
        """Semi-explicit index-1 DAE (eq. 2.166-2.168, 2.187): (f, g) with the same f as
        :meth:`index3_dae` and g = a vdot + (d(a v)/dq) v + 2 alpha cdot + alpha^2 c."""
        alpha = self.baumgarte if baumgarte is None else _checked_baumgarte(baumgarte)

        def g(t, x, z, u=None):
            xdot, c, a, cdot, curv = self._dynamics_with_multipliers(x, z, u)
            res = (a @ xdot[..., self.nq :].unsqueeze(-1)).squeeze(-1) + curv
            if alpha is not None:
                res = res + 2 * alpha * cdot + alpha**2 * c
            return res

        return self._f_with_multipliers, g

    def project_consistent(self, q, qdot, tol: float = 1e-12, max_iter: int = 50):
        """Least-norm projection of (q, qdot) onto C(q, qdot) = 0 (eq. 2.182).

        Positions: Gauss-Newton on ``min 0.5 |c(q)|^2`` by :func:`integrators.newton.minimize`;
        with nc < nq constraints ``a^T a`` (a = dc/dq) is singular and a small shift ``alpha I``
        (eq. 3.61) makes each step ``-a^T (a a^T + alpha I)^-1 c``, the least-norm step
        ``-a^T (a a^T)^-1 c`` up to a relative ``alpha / sigma_min(a)^2``, until ``|c| <= tol``.
        Velocities: qdot <- qdot - a^T (a a^T)^-1 a qdot (made tangent, Fig. 2.9).
        Raises SingularMatrixError where a a^T is singular and ConvergenceError naming the
        samples with ``|c| > tol`` after ``max_iter`` steps.
        """
        self._check_args("project_consistent", q=q, qdot=qdot)
        eps = torch.finfo(q.dtype).eps
        fit = minimize(
            lambda qq: self.constraints(qq),
            q,
            method="gauss_newton",
            regularization=eps**0.5,
            line_search=False,  # full Gauss-Newton steps
            tol=0.0,  # stop once the steps reach the rounding level; |c| is checked below
            xtol=10 * eps,
            max_iter=max_iter,
        )
        q = fit.theta
        c, a, _, _ = self.constraint_terms(q, torch.zeros_like(qdot))
        gram = a @ a.transpose(-1, -2)
        cdot = (a @ qdot.unsqueeze(-1)).squeeze(-1)
        step = _solve(gram, cdot, "a a^T (constraint gradients are dependent)", strict=True)
        bad = c.detach().abs().amax(-1) > tol
        if bool(bad.any()):
            raise ConvergenceError(
                f"project_consistent: |c(q)| > {tol:g} after {max_iter} Gauss-Newton steps at "
                f"batch indices {torch.nonzero(bad)[:5].tolist()}; start closer to the "
                "constraint manifold"
            )
        qdot = qdot - (a.transpose(-1, -2) @ step.unsqueeze(-1)).squeeze(-1)
        return q, qdot

    def linearize(self, q_eq, u_eq=None):
        """A (*batch, 2 nq, 2 nq), B (*batch, 2 nq, nu) of xdot = f(x, u) at an equilibrium
        (q_eq, qdot = 0, u_eq) (eq. 1.35); ``u_eq`` None: zero inputs (B still has its nu
        columns)."""
        from .linearize import linearize

        x = torch.cat([q_eq, torch.zeros_like(q_eq)], -1)
        if u_eq is None and self.nu > 0:
            u_eq = q_eq.new_zeros(*q_eq.shape[:-1], self.nu)
        a, b, _, _ = linearize(self, x, u_eq)
        return a, b
