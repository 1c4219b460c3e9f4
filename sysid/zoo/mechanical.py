"""Mechanical plants of the notes (chapter 2, §1.5), each built with LagrangianSystem.

Every plant is a :class:`sysid.mechanics.LagrangianSystem` (so ``forward(t, x, u)`` is the explicit
first-order ODE in x = [q, qdot], whose entries ``state_names`` lists: the coordinate names, then
the same names with ``dot``; the first line of each class docstring gives them) with physical
parameters as ``nn.Parameter``, and also carries the notes' closed form transcribed by hand
(``closed_form_acceleration``, and for constrained plants ``closed_form_kkt`` giving M(q) and the
right-hand side of eq. 2.168) so tests can compare the autograd builder with the notes. Typos of the
notes that were found by those comparisons are fixed in the closed forms and listed in each
docstring.

Inputs (``u`` of shape (*batch, 1)): the notes give no inputs for most plants; where a plant
has one here it is a horizontal force on the cart (crane family) or a force on the mass, added
through eq. (2.115) and documented as an addition.

Masses, rigid rod lengths and the elastic cranes' rest lengths L0 must be > 0, the counts
n_masses and n_nodes integers >= 1 and a Baumgarte gain >= 0, at construction
(InputValidationError otherwise). A
fit that drives one to zero or below is not stopped: a singular W(q) then gives NaN
accelerations for the affected batch members (with an RKIdentWarning where W is not diagonal;
inf/NaN from the division where it is), which the integrators report as NON_FINITE.
"""

import torch

from integrators._options import check_int

from ..mechanics import LagrangianSystem, distributed_body, spring_potential
from ._params import as_parameter, like, like_component, stack_last


def _u(u, q):
    """The input (*batch, nu) on q's batch (an input shared by the batch is broadcast)."""
    if u is None:
        return torch.zeros_like(q[..., :1])
    u = u.to(q)
    return u.expand(*torch.broadcast_shapes(q.shape[:-1], u.shape[:-1]), u.shape[-1])


def _force_on_first(u, q):
    """Generalized force (u, 0, ..., 0), the input acting on the first coordinate: (*batch, nq)
    on the batch of q and u."""
    f = _u(u, q)
    return torch.cat([f, torch.zeros_like(q[..., 1:]).expand(*f.shape[:-1], -1)], -1)


def _horizontal_force(u, q):
    """Force (u, 0) on one point, shape (*batch, 1, 2)."""
    f = _u(u, q)
    return torch.stack([f[..., 0], torch.zeros_like(f[..., 0])], -1).unsqueeze(-2)


def _mat(rows):
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


class SpringMass(LagrangianSystem):
    """Vertical spring-mass, state (x, xdot), x downwards from the spring rest length:

    eq. (2.45)-(2.54), q = x, T = m xdot^2 / 2, V = -m g x + k x^2 / 2, hence m xddot = m g - k x
    (eq. 2.53). Optional input: a downward force u on the mass (an addition, through eq. 2.115)."""

    def __init__(self, m=1.0, k=10.0, g=9.81):
        super().__init__(nq=1, nu=1, coordinate_names=("x",))
        self.m, self.k, self.g = (
            as_parameter(m, "m", positive=True),
            as_parameter(k, "k"),
            as_parameter(g, "g"),
        )

    def diagonal_mass(self):
        return self.m.reshape(1) if self.m.dim() == 0 else self.m  # (1,) or (*batch, 1)

    def potential(self, q):
        # q (*batch, 1) against parameters of shape () or (*batch, 1): sum the last axis
        m, g, k = like(self.m, q), like(self.g, q), like(self.k, q)
        return (-m * g * q + 0.5 * k * q**2).sum(-1)

    def generalized_force(self, q, qdot, u):
        return _u(u, q)

    def closed_form_acceleration(self, q, qdot, u=None):
        m, k, g = like(self.m, q), like(self.k, q), like(self.g, q)
        return g - k / m * q + _u(u, q) / m  # eq. (2.53)


class SpringMassDamper(LagrangianSystem):
    """Spring-mass-damper, state (y, ydot), eq. (1.26)-(1.28): m yddot + xi ydot + K y = u.

    The damper enters as the generalised force -xi ydot and the input as a force u
    (eq. 2.112)."""

    def __init__(self, m=1.0, xi=0.5, K=4.0):
        super().__init__(nq=1, nu=1, coordinate_names=("y",))
        self.m, self.xi, self.K = (
            as_parameter(m, "m", positive=True),
            as_parameter(xi, "xi"),
            as_parameter(K, "K"),
        )

    def diagonal_mass(self):
        return self.m.reshape(1) if self.m.dim() == 0 else self.m  # (1,) or (*batch, 1)

    def potential(self, q):
        # q (*batch, 1) against K of shape () or (*batch, 1): sum the last axis
        return (0.5 * like(self.K, q) * q**2).sum(-1)

    def generalized_force(self, q, qdot, u):
        return _u(u, q) - like(self.xi, q) * qdot

    def closed_form_acceleration(self, q, qdot, u=None):
        m, xi, k = like(self.m, q), like(self.xi, q), like(self.K, q)
        return (_u(u, q) - xi * qdot - k * q) / m  # eq. (1.28)


class _CartCrane(LagrangianSystem):
    """Crane plants in polar coordinates: point 0 is the cart, gravity acts along -y on the
    point masses, and the input u is a horizontal force on the cart (eq. 2.115)."""

    def gravity(self):
        return stack_last(torch.zeros_like(self.g), -self.g)

    def force_points(self, q):
        return self.positions(q)[..., :1, :]

    def point_forces(self, q, qdot, u):
        return _horizontal_force(u, q)


class Crane(_CartCrane):
    """Crane in polar coordinates, state (x, theta, xdot, thetadot), eq. (2.55)-(2.70).

    q = (x, theta), cart M at (x, 0), hanging mass m at p_m = (x + L sin theta, -L cos theta)
    (eq. 2.56), V = -m g L cos theta (eq. 2.62). W(q) of eq. (2.60); accelerations eq. (2.70)
    (checked: no typo). Input: horizontal force u on the cart (an addition; eq. 2.115 gives
    Q = (u, 0))."""

    def __init__(self, M=1.0, m=0.5, L=1.0, g=9.81):
        super().__init__(nq=2, nu=1, coordinate_names=("x", "theta"))
        self.M, self.m = as_parameter(M, "M", positive=True), as_parameter(m, "m", positive=True)
        self.L, self.g = as_parameter(L, "L", positive=True), as_parameter(g, "g")

    def point_masses(self):
        return stack_last(self.M, self.m)

    def positions(self, q):
        x, th, length = q[..., 0], q[..., 1], like_component(self.L, q)
        cart = torch.stack([x, torch.zeros_like(x)], -1)
        bob = torch.stack([x + length * torch.sin(th), -length * torch.cos(th)], -1)
        return torch.stack(torch.broadcast_tensors(cart, bob), -2)  # L may be per member

    def closed_form_mass_matrix(self, q):
        M, m, L = like(self.M, q), like(self.m, q), like(self.L, q)
        c = torch.cos(q[..., 1])
        return _mat([[M + m + 0 * c, m * L * c], [m * L * c, m * L**2 + 0 * c]])  # eq. (2.60)

    def closed_form_acceleration(self, q, qdot, u=None):
        M, m, L, g = like(self.M, q), like(self.m, q), like(self.L, q), like(self.g, q)
        s, c, thd = torch.sin(q[..., 1]), torch.cos(q[..., 1]), qdot[..., 1]
        den = M + m - m * c**2
        qdd = torch.stack(
            [m * s * (L * thd**2 + g * c) / den, -s / L * ((M + m) * g + m * L * c * thd**2) / den],
            -1,
        )  # eq. (2.70)
        f = _u(u, q)[..., 0]
        force = torch.stack([f, torch.zeros_like(f)], -1)
        return (
            qdd + torch.linalg.solve(self.closed_form_mass_matrix(q), force.unsqueeze(-1))[..., 0]
        )


class ElasticCranePolar(_CartCrane):
    """Elastic crane, polar, state (x, theta, L, xdot, thetadot, Ldot), eq. (2.71)-(2.81).

    q = (x, theta, L), cart M at (x, 0), hanging mass m at (x + L sin theta, -L cos theta), rod
    energy K (L - L0)^2 / 2 (eq. 2.71), gravity V = -m g L cos theta (eq. 2.77). W(q) of eq. (2.76)
    and the vector of eq. (2.80) were checked against the autograd builder and are right as printed;
    accelerations by eq. (2.81). Input: horizontal force u on the cart (addition)."""

    def __init__(self, M=1.0, m=0.5, L0=1.0, K=50.0, g=9.81):
        super().__init__(nq=3, nu=1, coordinate_names=("x", "theta", "L"))
        self.M, self.m = as_parameter(M, "M", positive=True), as_parameter(m, "m", positive=True)
        self.L0 = as_parameter(L0, "L0", positive=True)
        self.K, self.g = as_parameter(K, "K"), as_parameter(g, "g")

    def point_masses(self):
        return stack_last(self.M, self.m)

    def positions(self, q):
        x, th, length = q[..., 0], q[..., 1], q[..., 2]
        cart = torch.stack([x, torch.zeros_like(x)], -1)
        bob = torch.stack([x + length * torch.sin(th), -length * torch.cos(th)], -1)
        return torch.stack([cart, bob], -2)

    def potential(self, q):
        K, L0 = like_component(self.K, q), like_component(self.L0, q)
        return 0.5 * K * (q[..., 2] - L0) ** 2  # eq. (2.71)

    def closed_form_mass_matrix(self, q):
        M, m = like(self.M, q), like(self.m, q)
        th, length = q[..., 1], q[..., 2]
        s, c, z = torch.sin(th), torch.cos(th), torch.zeros_like(th)
        return _mat(
            [
                [M + m + z, m * length * c, m * s],
                [m * length * c, m * length**2, z],
                [m * s, z, m + z],
            ]
        )  # eq. (2.76)

    def closed_form_acceleration(self, q, qdot, u=None):
        m, K, L0, g = like(self.m, q), like(self.K, q), like(self.L0, q), like(self.g, q)
        th, length = q[..., 1], q[..., 2]
        thd, ld = qdot[..., 1], qdot[..., 2]
        s, c = torch.sin(th), torch.cos(th)
        h = torch.stack(
            [
                m * thd * (2 * ld * c - length * thd * s),
                m * length * (2 * ld * thd + g * s),
                -m * length * thd**2 + K * (length - L0) - m * g * c,
            ],
            -1,
        )  # eq. (2.80)
        f = _u(u, q)[..., 0]
        force = torch.stack([f, torch.zeros_like(f), torch.zeros_like(f)], -1)
        return torch.linalg.solve(self.closed_form_mass_matrix(q), (force - h).unsqueeze(-1))[
            ..., 0
        ]  # eq. (2.81)


class ElasticCraneCartesian(LagrangianSystem):
    """Elastic crane, Cartesian, state (x, p1, p2, xdot, p1dot, p2dot), p2 down, eq. (2.82)-(2.90).

    q = (x, p1, p2) with the vertical axis p2 pointing down (Fig. 2.5), W = diag(M, m, m)
    (eq. 2.85), rod energy K (L - L0)^2 / 2 with L = ||p - (x, 0)|| (eq. 2.86), gravity
    V = -m g p2 (eq. 2.87).

    Typo fixed: eq. (2.88) writes "- m g p2" in L = T - V; with V = -m g p2 it is "+ m g p2"
    (eq. 2.89c and 2.90 already use the right sign). Accelerations eq. (2.90). Input:
    horizontal force u on the cart (addition)."""

    def __init__(self, M=1.0, m=0.5, L0=1.0, K=50.0, g=9.81):
        super().__init__(nq=3, nu=1, coordinate_names=("x", "p1", "p2"))
        self.M, self.m = as_parameter(M, "M", positive=True), as_parameter(m, "m", positive=True)
        self.L0 = as_parameter(L0, "L0", positive=True)
        self.K, self.g = as_parameter(K, "K"), as_parameter(g, "g")

    def diagonal_mass(self):
        return stack_last(self.M, self.m, self.m)

    def potential(self, q):
        x, p = q[..., 0], q[..., 1:]
        anchor = torch.stack([x, torch.zeros_like(x)], -1)
        K, L0 = like_component(self.K, q), like_component(self.L0, q)
        rod = spring_potential(anchor, p, K, L0)
        return rod - like_component(self.m, q) * like_component(self.g, q) * q[..., 2]

    def generalized_force(self, q, qdot, u):
        f = _u(u, q)
        return torch.cat([f, torch.zeros_like(q[..., 1:])], -1)

    def closed_form_acceleration(self, q, qdot, u=None):
        M, m, K, L0, g = (like(p, q) for p in (self.M, self.m, self.K, self.L0, self.g))
        x, p1, p2 = q[..., 0], q[..., 1], q[..., 2]
        length = torch.sqrt((p1 - x) ** 2 + p2**2)
        k = K * (length - L0) / length
        f = _u(u, q)[..., 0]
        return torch.stack(
            [k * (p1 - x) / M + f / M, k * (x - p1) / m, g - k * p2 / m], -1
        )  # eq. (2.90)


class RigidCraneCartesian(LagrangianSystem):
    """Rigid-rod crane, Cartesian, state (x, p1, p2, xdot, p1dot, p2dot), p2 down, constrained.

    Eq. (2.138)-(2.149) and its index-1 form eq. (2.175)-(2.178): q = (x, p1, p2) (p2 down),
    W = diag(M, m, m), V = -m g p2, c(q) = (delta^T delta - L^2)/2 with delta = p - (x, 0)
    (eq. 2.145).

    Typos fixed in eq. (2.178): M(q) is [[W, a^T], [a, 0]] with a = (x - p1, p1 - x, p2) (the
    printed block rows are garbled), and the last right-hand-side entry is
    -(xdot^2 + p1dot^2 + p2dot^2 - 2 xdot p1dot) = -deltadot^T deltadot (the printed sign is
    wrong: a qddot = -deltadot^T deltadot from eq. 2.177c). Input: horizontal force u on the
    cart (addition)."""

    def __init__(self, M=1.0, m=0.5, L=1.0, g=9.81, baumgarte=None):
        super().__init__(nq=3, nu=1, baumgarte=baumgarte, coordinate_names=("x", "p1", "p2"))
        self.M, self.m = as_parameter(M, "M", positive=True), as_parameter(m, "m", positive=True)
        self.L, self.g = as_parameter(L, "L", positive=True), as_parameter(g, "g")

    def diagonal_mass(self):
        return stack_last(self.M, self.m, self.m)

    def potential(self, q):
        m, g = like_component(self.m, q), like_component(self.g, q)
        return -m * g * q[..., 2]  # eq. (2.142)

    def generalized_force(self, q, qdot, u):
        return _force_on_first(u, q)

    def constraints(self, q):
        delta = torch.stack([q[..., 1] - q[..., 0], q[..., 2]], -1)
        return (0.5 * ((delta * delta).sum(-1) - like_component(self.L, q) ** 2)).unsqueeze(-1)

    def closed_form_kkt(self, q, qdot, u=None):
        """M(q) (*batch, 4, 4) and right-hand side (*batch, 4) of eq. (2.178), typos fixed."""
        M, m, g = like(self.M, q), like(self.m, q), like(self.g, q)
        x, p1, p2 = q[..., 0], q[..., 1], q[..., 2]
        xd, p1d, p2d = qdot[..., 0], qdot[..., 1], qdot[..., 2]
        z = torch.zeros_like(x)
        kkt = _mat(
            [
                [M + z, z, z, x - p1],
                [z, m + z, z, p1 - x],
                [z, z, m + z, p2],
                [x - p1, p1 - x, p2, z],
            ]
        )
        rhs = torch.stack(
            [_u(u, q)[..., 0], z, m * g + z, -(xd**2 + p1d**2 + p2d**2 - 2 * xd * p1d)], -1
        )
        return kkt, rhs

    def closed_form_acceleration(self, q, qdot, u=None):
        """(qddot, z) from eq. (2.178)."""
        kkt, rhs = self.closed_form_kkt(q, qdot, u)
        sol = torch.linalg.solve(kkt, rhs.unsqueeze(-1))[..., 0]
        return sol[..., :3], sol[..., 3:]


class TwoPendulumCranePolar(_CartCrane):
    """Two-pendulum crane, polar, state (x, theta1, theta2, xdot, theta1dot, theta2dot).

    Eq. (2.98)-(2.109): q = (x, theta1, theta2), cart and both hanging masses of mass m, rods of
    length L, p1 = (x, 0) + R(theta1)(0, -L), p2 = p1 + R(theta2)(0, -L) (eq. 2.99-2.102),
    V = m g (p1_y + p2_y) (eq. 2.106).

    Typos fixed: in W(q) of eq. (2.105) the (2, 1) entry is 2 L cos theta1 (printed
    cos theta2: a transposed entry, W must be symmetric) and the (2, 3), (3, 2) entries are
    L^2 cos(theta1 - theta2) (printed L cos(...)); the convective term eq. (2.108) has the
    wrong overall sign (it is -m L [...]). Eq. (2.107c) is right. Input: horizontal force u on
    the cart (addition)."""

    def __init__(self, m=1.0, L=1.0, g=9.81):
        super().__init__(nq=3, nu=1, coordinate_names=("x", "theta1", "theta2"))
        self.m, self.L, self.g = (
            as_parameter(m, "m", positive=True),
            as_parameter(L, "L", positive=True),
            as_parameter(g, "g"),
        )

    def point_masses(self):
        return stack_last(self.m, self.m, self.m)

    def positions(self, q):
        x, t1, t2, length = q[..., 0], q[..., 1], q[..., 2], like(self.L, q)
        p0 = torch.stack([x, torch.zeros_like(x)], -1)
        p1 = p0 + length * torch.stack([torch.sin(t1), -torch.cos(t1)], -1)
        p2 = p1 + length * torch.stack([torch.sin(t2), -torch.cos(t2)], -1)
        return torch.stack(torch.broadcast_tensors(p0, p1, p2), -2)  # L may be per member

    def closed_form_mass_matrix(self, q):
        m, L = like(self.m, q), like(self.L, q)
        t1, t2 = q[..., 1], q[..., 2]
        c1, c2, c12 = torch.cos(t1), torch.cos(t2), torch.cos(t1 - t2)
        three = 3 + 0 * t1
        return m * _mat(
            [
                [three, 2 * L * c1, L * c2],
                [2 * L * c1, 2 * L**2 + 0 * t1, L**2 * c12],
                [L * c2, L**2 * c12, L**2 + 0 * t1],
            ]
        )  # eq. (2.105), typos fixed

    def closed_form_acceleration(self, q, qdot, u=None):
        m, L, g = like(self.m, q), like(self.L, q), like(self.g, q)
        t1, t2 = q[..., 1], q[..., 2]
        xd, w1, w2 = qdot[..., 0], qdot[..., 1], qdot[..., 2]
        s1, s2, s12 = torch.sin(t1), torch.sin(t2), torch.sin(t1 - t2)
        grad_l = (
            -m
            * L
            * torch.stack(
                [
                    torch.zeros_like(t1),
                    2 * g * s1 + 2 * w1 * xd * s1 + L * w1 * w2 * s12,
                    g * s2 + w2 * xd * s2 - L * w1 * w2 * s12,
                ],
                -1,
            )
        )  # eq. (2.107c)
        convective = (
            -m
            * L
            * torch.stack(
                [
                    2 * s1 * w1**2 + s2 * w2**2,
                    L * w1 * w2 * s12 + 2 * xd * w1 * s1 - L * w2**2 * s12,
                    -L * w1 * w2 * s12 + xd * w2 * s2 + L * w1**2 * s12,
                ],
                -1,
            )
        )  # eq. (2.108) with its sign fixed
        f = _u(u, q)[..., 0]
        force = torch.stack([f, torch.zeros_like(f), torch.zeros_like(f)], -1)
        rhs = force + grad_l - convective
        return torch.linalg.solve(self.closed_form_mass_matrix(q), rhs.unsqueeze(-1))[..., 0]


class TwoPendulumCraneCartesian(LagrangianSystem):
    """Two-pendulum crane, Cartesian, state (x, p1x, p1y, p2x, p2y, then rates ...dot), y down.

    Constrained coordinates, eq. (2.150)-(2.158): q = (x, p1, p2) in R^5 with the points
    p1 = (p1x, p1y), p2 = (p2x, p2y) (vertical axes pointing down), W = m I (eq. 2.151; the notes
    say "3x3 identity", it is 5x5), V = -m g (p1_y + p2_y) (eq. 2.152), constraints
    ``c = (|delta1|^2 - L^2, |delta2|^2 - L^2)/2`` with delta1 = (x, 0) - p1, delta2 = p2 - p1
    (eq. 2.153-2.154); explicit form eq. (2.157). Input: horizontal force u on the cart."""

    def __init__(self, m=1.0, L=1.0, g=9.81, baumgarte=None):
        super().__init__(
            nq=5,
            nu=1,
            baumgarte=baumgarte,
            coordinate_names=("x", "p1x", "p1y", "p2x", "p2y"),
        )
        self.m, self.L, self.g = (
            as_parameter(m, "m", positive=True),
            as_parameter(L, "L", positive=True),
            as_parameter(g, "g"),
        )

    def diagonal_mass(self):
        return self.m * torch.ones(5, dtype=self.m.dtype)

    def potential(self, q):
        m, g = like_component(self.m, q), like_component(self.g, q)
        return -m * g * (q[..., 2] + q[..., 4])

    def generalized_force(self, q, qdot, u):
        return _force_on_first(u, q)

    def constraints(self, q):
        x, p1, p2 = q[..., 0], q[..., 1:3], q[..., 3:5]
        d1 = torch.stack([x, torch.zeros_like(x)], -1) - p1
        d2 = p2 - p1
        L2 = like_component(self.L, q) ** 2
        return 0.5 * torch.stack([(d1 * d1).sum(-1) - L2, (d2 * d2).sum(-1) - L2], -1)

    def closed_form_kkt(self, q, qdot, u=None):
        """M(q) (*batch, 7, 7) and right-hand side of the index-1 form of eq. (2.156)-(2.158)."""
        m, g = like(self.m, q), like(self.g, q)
        x, p1, p2 = q[..., 0], q[..., 1:3], q[..., 3:5]
        xd, p1d, p2d = qdot[..., 0], qdot[..., 1:3], qdot[..., 3:5]
        d1 = torch.stack([x, torch.zeros_like(x)], -1) - p1
        d2 = p2 - p1
        z = torch.zeros_like(x)
        col1 = torch.stack([x - p1[..., 0], -d1[..., 0], -d1[..., 1], z, z], -1)  # eq. (2.156c)
        col2 = torch.stack([z, -d2[..., 0], -d2[..., 1], d2[..., 0], d2[..., 1]], -1)
        a_t = torch.stack([col1, col2], -1)  # (*, 5, 2)
        w = m * torch.eye(5, dtype=q.dtype, device=q.device).expand(*q.shape[:-1], 5, 5)
        top = torch.cat([w, a_t], -1)
        bottom = torch.cat([a_t.transpose(-1, -2), q.new_zeros(*q.shape[:-1], 2, 2)], -1)
        d1d = torch.stack([xd, torch.zeros_like(xd)], -1) - p1d
        d2d = p2d - p1d
        rhs = torch.stack(
            [
                _u(u, q)[..., 0],
                z,
                m * g + z,
                z,
                m * g + z,
                -(d1d * d1d).sum(-1),
                -(d2d * d2d).sum(-1),
            ],
            -1,
        )
        return torch.cat([top, bottom], -2), rhs

    def closed_form_acceleration(self, q, qdot, u=None):
        kkt, rhs = self.closed_form_kkt(q, qdot, u)
        sol = torch.linalg.solve(kkt, rhs.unsqueeze(-1))[..., 0]
        return sol[..., :5], sol[..., 5:]


class HangingChain(LagrangianSystem):
    """Hanging chain of N masses in 3-D, state (x1, y1, z1, .., xN, yN, zN, then rates ...dot).

    Elastic chain, eq. (2.91)-(2.97): q = (p_1, ..., p_N) in R^{3N}, p_k = (xk, yk, zk) (z axis
    up), W = m I (eq. 2.92), V = m g sum_k z_k + K/2 sum_{k=0}^N
    ``|p_{k+1} - p_k|^2`` with fixed ends p_0, p_{N+1} (eq. 2.93, rest length 0).

    Typos fixed: eq. (2.95c) has +m g (it is -m g e_z: gravity pulls down) and eq. (2.96)-(2.97)
    flip the sign of the spring terms; correct is
    qddot_k = K/m (p_{k-1} - p_k) + K/m (p_{k+1} - p_k) - g e_z."""

    def __init__(
        self, n_masses=10, m=0.1, K=10.0, g=9.81, p_start=(0.0, 0.0, 0.0), p_end=(1.0, 0.0, 0.0)
    ):
        n_masses = check_int(n_masses, "HangingChain: n_masses")
        names = [f"{axis}{k + 1}" for k in range(n_masses) for axis in "xyz"]
        super().__init__(nq=3 * n_masses, coordinate_names=names)
        self.n_masses = n_masses
        self.m, self.K, self.g = (
            as_parameter(m, "m", positive=True),
            as_parameter(K, "K"),
            as_parameter(g, "g"),
        )
        self.p_start = as_parameter(p_start, "p_start", vector=True)
        self.p_end = as_parameter(p_end, "p_end", vector=True)

    def diagonal_mass(self):
        return self.m * torch.ones(self.nq, dtype=self.m.dtype)

    def _with_ends(self, q):
        p = q.reshape(*q.shape[:-1], self.n_masses, 3)
        start = like(self.p_start, q).expand(*q.shape[:-1], 1, 3)
        end = like(self.p_end, q).expand(*q.shape[:-1], 1, 3)
        return torch.cat([start, p, end], -2)

    def potential(self, q):
        p = self._with_ends(q)
        delta = p[..., 1:, :] - p[..., :-1, :]
        K, m, g = (like_component(v, q) for v in (self.K, self.m, self.g))
        links = 0.5 * K * (delta * delta).sum((-1, -2))  # eq. (2.93), L0 = 0
        return links + m * g * q[..., 2::3].sum(-1)

    def closed_form_acceleration(self, q, qdot=None, u=None):
        p = self._with_ends(q)
        k_over_m = like(self.K, q) / like(self.m, q)
        acc = k_over_m * (p[..., :-2, :] - p[..., 1:-1, :]) + k_over_m * (
            p[..., 2:, :] - p[..., 1:-1, :]
        )  # eq. (2.97), signs fixed
        acc = acc - like(self.g, q) * torch.tensor([0.0, 0.0, 1.0], dtype=q.dtype, device=q.device)
        return acc.reshape(q.shape)


class Bowl(LagrangianSystem):
    """Mass sliding in a bowl, state (p1, p2, p3, p1dot, p2dot, p3dot), p3 up, constrained.

    Eq. (2.123)-(2.137) and index-1 form eq. (2.170)-(2.174): q = p in R^3 (z up),
    ``T = m |pdot|^2 / 2``, V = m g p3 (eq. 2.133), c = p3 - (p1^2 + p2^2)/4 (eq. 2.123).
    det M(q) = -m^2 (p1^2 + p2^2 + 4)/4 (eq. 2.174).

    Typo fixed in eq. (2.173): the last right-hand-side entry is (p1dot^2 + p2dot^2)/2 (a factor
    1/2 is missing: from eq. 2.171c, a qddot = (p1dot^2 + p2dot^2)/2); the right-hand side's
    third entry is -m g (gravity, eq. 2.172a; printed +m g). Input: none."""

    def __init__(self, m=1.0, g=9.81, baumgarte=None):
        super().__init__(nq=3, baumgarte=baumgarte, coordinate_names=("p1", "p2", "p3"))
        self.m, self.g = as_parameter(m, "m", positive=True), as_parameter(g, "g")

    def diagonal_mass(self):
        return self.m * torch.ones(3, dtype=self.m.dtype)

    def potential(self, q):
        return like_component(self.m, q) * like_component(self.g, q) * q[..., 2]

    def constraints(self, q):
        return (q[..., 2] - 0.25 * (q[..., 0] ** 2 + q[..., 1] ** 2)).unsqueeze(-1)

    def closed_form_kkt(self, q, qdot, u=None):
        m, g = like(self.m, q), like(self.g, q)
        p1, p2 = q[..., 0], q[..., 1]
        z, one = torch.zeros_like(p1), torch.ones_like(p1)
        kkt = _mat(
            [
                [m + z, z, z, -0.5 * p1],
                [z, m + z, z, -0.5 * p2],
                [z, z, m + z, one],
                [-0.5 * p1, -0.5 * p2, one, z],
            ]
        )
        rhs = torch.stack([z, z, -m * g + z, 0.5 * (qdot[..., 0] ** 2 + qdot[..., 1] ** 2)], -1)
        return kkt, rhs

    def closed_form_kkt_determinant(self, q):
        m = like(self.m, q)
        return -(m**2) / 4 * (q[..., 0] ** 2 + q[..., 1] ** 2 + 4)  # eq. (2.174)

    def closed_form_acceleration(self, q, qdot, u=None):
        kkt, rhs = self.closed_form_kkt(q, qdot, u)
        sol = torch.linalg.solve(kkt, rhs.unsqueeze(-1))[..., 0]
        return sol[..., :3], sol[..., 3:]


class DistributedRod(LagrangianSystem):
    """Rigid rod pivoting in a vertical plane, state (theta, thetadot), theta from the x axis.

    Uniformly distributed mass m, length L, pivoting at the origin in the vertical plane,
    q = theta measured from the horizontal x axis (eq. 2.17-2.24), built by
    Gauss-Legendre quadrature along the rod. Optional input: a torque u at the pivot.

    Typo fixed: eq. (2.19) misses the factor 1/2 of the kinetic energy (T = m L^2 thetadot^2 / 6)
    and eq. (2.20) then states W = 2/3 m L^2; correct is W = m L^2 / 3 (1/3 of the W of the
    mass concentrated at the tip, eq. 2.11). V = m g L sin(theta) / 2 (eq. 2.24) is right."""

    def __init__(self, m=1.0, L=1.0, g=9.81, n_nodes=2):
        super().__init__(nq=1, nu=1, coordinate_names=("theta",))
        self.m, self.L, self.g = (
            as_parameter(m, "m", positive=True),
            as_parameter(L, "L", positive=True),
            as_parameter(g, "g"),
        )
        self.n_nodes = check_int(n_nodes, "DistributedRod: n_nodes")

    def _body(self):
        def position(q, s):
            length = like(self.L, q)
            th = q[..., 0]
            return s * length * torch.stack([torch.cos(th), torch.sin(th)], -1)  # eq. (2.17)

        return distributed_body(self.m, position, self.n_nodes)

    def point_masses(self):
        return self._body()[0]

    def positions(self, q):
        return self._body()[1](q)

    def gravity(self):
        return stack_last(torch.zeros_like(self.g), -self.g)

    def generalized_force(self, q, qdot, u):
        return _u(u, q)

    def closed_form_acceleration(self, q, qdot, u=None):
        m, L, g = like(self.m, q), like(self.L, q), like(self.g, q)
        w = m * L**2 / 3
        return (-0.5 * m * g * L * torch.cos(q) + _u(u, q)) / w
