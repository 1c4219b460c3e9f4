"""sysid.mechanics.LagrangianSystem: builder invariants, forces, constraints, gradients."""

import pytest
import torch

from integrators import odeint
from integrators.errors import SingularMatrixError
from sysid.mechanics import LagrangianSystem, distributed_body, spring_potential
from sysid.zoo import Bowl, Crane, RigidCraneCartesian

DT = torch.float64
G = 9.81


def _pendulum_positions(q, length=1.2):
    th = q[..., 0]
    return (length * torch.stack([torch.sin(th), -torch.cos(th)], -1)).unsqueeze(-2)


def _random(n, nq, seed):
    gen = torch.Generator().manual_seed(seed)
    return torch.randn(n, nq, dtype=DT, generator=gen), torch.randn(n, nq, dtype=DT, generator=gen)


def test_three_ways_to_give_kinetic_energy_agree_with_pendulum_closed_form():
    m, length = 0.8, 1.2
    points = LagrangianSystem(
        1,
        point_masses=torch.tensor([m], dtype=DT),
        positions=_pendulum_positions,
        gravity=torch.tensor([0.0, -G], dtype=DT),
    )
    direct = LagrangianSystem(
        1,
        kinetic_energy=lambda q, qd: 0.5 * m * length**2 * qd[..., 0] ** 2,
        potential=lambda q: -m * G * length * torch.cos(q[..., 0]),
    )
    q, qd = _random(9, 1, 0)
    ref = -G / length * torch.sin(q)
    torch.testing.assert_close(points.accelerations(q, qd), ref, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(direct.accelerations(q, qd), ref, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(points.energy(q, qd), direct.energy(q, qd))


def test_gravity_as_point_force_equals_gravity_as_potential():
    """Eq. (2.115): Q = sum_i (dp_i/dq)^T F_i with F_i = m_i g gives the motion of V = m g z."""
    crane = Crane(M=1.5, m=0.6, L=0.8)
    masses = torch.tensor([1.5, 0.6], dtype=DT)

    def weights(q, qd, u):
        f = torch.zeros(*q.shape[:-1], 2, 2, dtype=q.dtype)
        f[..., 1] = -G * masses
        return f

    as_force = LagrangianSystem(
        2,
        point_masses=masses,
        positions=crane.positions,
        force_points=crane.positions,
        point_forces=weights,
    )
    q, qd = _random(12, 2, 1)
    torch.testing.assert_close(
        as_force.accelerations(q, qd), crane.accelerations(q, qd), rtol=1e-12, atol=1e-12
    )
    # the same for a constrained system: the bowl's weight as a force on p (Cartesian)
    bowl = Bowl(m=0.7)
    force_bowl = LagrangianSystem(
        3,
        diagonal_mass=0.7 * torch.ones(3, dtype=DT),
        force_points=lambda q: q.unsqueeze(-2),
        point_forces=lambda q, qd, u: torch.tensor([0.0, 0.0, -0.7 * G], dtype=DT).expand(
            *q.shape[:-1], 1, 3
        ),
        constraints=bowl.constraints,
    )
    q, qd = _random(12, 3, 2)
    a1, z1 = bowl.kkt_solve(q, qd)
    a2, z2 = force_bowl.kkt_solve(q, qd)
    torch.testing.assert_close(a1, a2, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(z1, z2, rtol=1e-12, atol=1e-12)


def test_distributed_body_and_spring_potential():
    masses, positions = distributed_body(
        torch.tensor(2.0, dtype=DT), lambda q, s: s * torch.stack([q[..., 0], q[..., 1]], -1), 3
    )
    torch.testing.assert_close(masses.sum(), torch.tensor(2.0, dtype=DT))
    q = torch.tensor([[0.3, -1.1]], dtype=DT)
    # centre of mass of a uniform segment from 0 to q is q / 2 (eq. 2.24)
    com = (masses[:, None] * positions(q)[0]).sum(0) / 2.0
    torch.testing.assert_close(com, q[0] / 2)
    a, b = torch.zeros(1, 2, dtype=DT), torch.tensor([[3.0, 4.0]], dtype=DT)
    torch.testing.assert_close(spring_potential(a, b, 2.0, 1.0), torch.tensor([16.0], dtype=DT))
    torch.testing.assert_close(spring_potential(a, b, 2.0), torch.tensor([25.0], dtype=DT))


def test_spring_with_a_tensor_rest_length_has_a_finite_force_where_its_ends_meet():
    """A rest length given as a tensor (a parameter to identify) formed the norm, whose
    derivative 0 * inf made the force NaN where the ends coincide (a number L0 = 0 never forms
    it). Its gradient is now that of the number form: 0 there, k (p_b - p_a) elsewhere for
    L0 = 0, and k (1 - L0 / r) (p_b - p_a) for L0 = 0.5 (hand formula)."""
    a = torch.tensor([[0.0, 0.0], [0.0, 0.0], [1.0, 2.0]], dtype=DT)
    b = torch.tensor([[0.0, 0.0], [0.3, -0.4], [1.0, 2.0]], dtype=DT, requires_grad=True)
    for L0 in (0.0, 0.5):
        energy = spring_potential(a, b, 3.0, torch.tensor(L0, dtype=DT, requires_grad=True))
        (grad,) = torch.autograd.grad(energy.sum(), b)
        assert bool(torch.isfinite(grad).all())
        delta = (b - a).detach()
        r = delta.norm(dim=-1, keepdim=True)
        expected = torch.where(r > 0, 3.0 * (1 - L0 / r.clamp_min(1e-300)) * delta, 0.0)
        torch.testing.assert_close(grad, expected)
        torch.testing.assert_close(energy, 1.5 * (r[:, 0] - L0) ** 2)


def test_implicit_residual_vanishes_at_explicit_derivative():
    crane = Crane()
    q, qd = _random(5, 2, 3)
    x = torch.cat([q, qd], -1)
    u = torch.randn(5, 1, dtype=DT)
    xdot = crane(torch.tensor(0.0), x, u)
    res = crane.implicit_residual(torch.tensor(0.0), xdot, x, u)
    torch.testing.assert_close(res, torch.zeros_like(res), rtol=0, atol=1e-12)


def test_dae_forms_and_consistency_projection():
    plant = RigidCraneCartesian(L=1.1)
    q, qd = _random(6, 3, 4)
    q[:, 2] = q[:, 2].abs() + 0.5
    q, qd = plant.project_consistent(q, qd)
    cons = plant.consistency(q, qd)
    torch.testing.assert_close(cons, torch.zeros_like(cons), rtol=0, atol=1e-10)
    qdd, z = plant.kkt_solve(q, qd)
    x = torch.cat([q, qd], -1)
    f1, g1 = plant.index1_dae()
    f3, g3 = plant.index3_dae()
    torch.testing.assert_close(f1(0.0, x, z)[..., 3:], qdd)
    g = g1(0.0, x, z)
    torch.testing.assert_close(g, torch.zeros_like(g), rtol=0, atol=1e-10)
    torch.testing.assert_close(g3(0.0, x, z), plant.constraints(q))
    # the least-norm projection moves a consistent state nowhere
    q2, qd2 = plant.project_consistent(q, qd)
    torch.testing.assert_close(q2, q)
    torch.testing.assert_close(qd2, qd)


def test_index1_algebraic_equation_differentiates_in_the_multipliers_alone():
    """g of the index-1 form (eq. 2.187) is affine in z with dg/dz = -a W^-1 a^T (eq. 2.168):
    autograd through g where only z carries a history (the state is data) gives that matrix,
    although the curvature term of the crane's quadratic constraint depends on neither."""
    plant = RigidCraneCartesian(L=1.1, baumgarte=2.0)
    q, qd = _random(2, 3, 7)
    q[:, 2] = q[:, 2].abs() + 0.5
    q, qd = plant.project_consistent(q, qd)
    x = torch.cat([q, qd], -1)
    z_leaf = torch.randn(2, 1, dtype=DT, requires_grad=True)
    _, g = plant.index1_dae()
    dg_dz = torch.autograd.grad(g(0.0, x, 1.0 * z_leaf).sum(), z_leaf)[0]
    _, a, _, _ = plant.constraint_terms(q, qd)
    mass = plant.mass_matrix(q)
    expected = -(a @ torch.linalg.solve(mass, a.transpose(-1, -2)))[..., 0, :]
    torch.testing.assert_close(dg_dz, expected, rtol=1e-12, atol=1e-12)


def _bowl_drift(alpha, dt=0.1, t_end=40.0):
    """max |c| over the first and second half of an RK4 run, and max |cdot|."""
    bowl = Bowl(baumgarte=alpha)
    q = torch.tensor([[1.0, 0.0, 0.25]], dtype=DT)
    qd = torch.tensor([[0.0, 1.5, 0.0]], dtype=DT)  # tangent: consistent (eq. 2.183)
    t = torch.arange(0.0, t_end + dt / 2, dt, dtype=DT)
    with torch.no_grad():
        sol = odeint(bowl, torch.cat([q, qd], -1), t, method="rk4", compile=False)
        c, cdot = bowl.drift(sol.x)
    half = len(t) // 2
    return c[0, :half].abs().max(), c[0, half:].abs().max(), cdot.abs().max()


def test_baumgarte_stabilisation_stops_constraint_drift():
    """Eq. (2.185)-(2.187), Fig. 2.10: with cddot = 0 the constraint drifts and keeps growing;
    with Baumgarte stabilisation (alpha = 1) it stays bounded at the integrator's accuracy."""
    first, second, _ = _bowl_drift(None)
    assert second > 2 * first and second > 1e-3
    first_s, second_s, cdot_s = _bowl_drift(1.0)
    assert second_s < second / 100
    assert second_s < 1.5 * first_s
    assert cdot_s < 1e-4


def test_gradients_through_simulation_match_finite_differences():
    """Differentiable end to end: d x(T) / d L and d x(T) / d x0 of an RK4 simulation."""
    t = torch.linspace(0.0, 0.5, 26, dtype=DT)

    def final(length, x0):
        return odeint(Crane(L=length), x0, t, method="rk4", compile=False).x[..., -1, :]

    x0 = torch.tensor([[0.1, 0.4, 0.0, -0.2]], dtype=DT, requires_grad=True)
    crane = Crane(L=0.9)
    out = odeint(crane, x0, t, method="rk4", compile=False).x[0, -1, 1]
    out.backward()
    h = 1e-6
    with torch.no_grad():
        fd_l = (final(0.9 + h, x0)[0, 1] - final(0.9 - h, x0)[0, 1]) / (2 * h)
        e = torch.zeros_like(x0)
        e[0, 1] = h
        fd_x = (final(0.9, x0 + e)[0, 1] - final(0.9, x0 - e)[0, 1]) / (2 * h)
    assert crane.L.grad.item() == pytest.approx(fd_l.item(), rel=1e-6)
    assert x0.grad[0, 1].item() == pytest.approx(fd_x.item(), rel=1e-6)


def test_linearisation_of_crane_at_rest():
    """Small oscillations: thetaddot = -(M + m) g / (M L) theta, xddot = m g / M theta."""
    M, m, L = 2.0, 0.5, 1.5
    a, b = Crane(M=M, m=m, L=L).linearize(torch.zeros(1, 2, dtype=DT), torch.zeros(1, 1, dtype=DT))
    ref = torch.zeros(4, 4, dtype=DT)
    ref[0, 2] = ref[1, 3] = 1.0
    ref[2, 1] = m * G / M
    ref[3, 1] = -(M + m) * G / (M * L)
    torch.testing.assert_close(a[0], ref, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(b[0, :, 0], torch.tensor([0, 0, 1 / M, -1 / (M * L)], dtype=DT))
    # without u_eq: zero inputs, and B keeps its input column (it came back (4, 0))
    a0, b0 = Crane(M=M, m=m, L=L).linearize(torch.zeros(1, 2, dtype=DT))
    torch.testing.assert_close(a0, a)
    torch.testing.assert_close(b0, b)


def test_projection_with_singular_constraint_gradients_raises_with_sample_index():
    """kkt_solve gives NaN for such a member (tests/test_mechanics_inputs.py); the projection
    cannot proceed and raises."""
    plant = RigidCraneCartesian()
    q = torch.tensor([[0.0, 0.5, 1.0], [0.3, 0.3, 0.0]], dtype=DT)  # sample 1: mass at the cart
    with pytest.raises(SingularMatrixError, match=r"a a\^T .* singular at batch index \[1\]"):
        plant.project_consistent(q, torch.zeros_like(q))


def test_float32_constrained():
    bowl = Bowl()
    q, qd = _random(4, 3, 5)
    a32, z32 = bowl.kkt_solve(q.float(), qd.float())
    a64, z64 = bowl.kkt_solve(q, qd)
    assert a32.dtype == torch.float32
    torch.testing.assert_close(a32.double(), a64, rtol=1e-4, atol=1e-4)


@pytest.mark.slow
def test_index1_dae_form_runs_in_daeint_and_matches_the_explicit_kkt_ode():
    from integrators import daeint
    from integrators.problems import SemiExplicitDAE

    bowl = Bowl(baumgarte=1.0)
    f, g = bowl.index1_dae()
    x0 = torch.tensor([[1.0, 0.0, 0.25, 0.0, 1.5, 0.0]], dtype=DT)
    with torch.no_grad():
        sol = daeint(
            SemiExplicitDAE(f, g),
            x0,
            torch.zeros(1, 1, dtype=DT),
            torch.linspace(0, 1, 11, dtype=DT),
            method="radau_iia",
            stages=3,
        )
        ref = odeint(bowl, x0, torch.linspace(0, 1, 201, dtype=DT), method="rk4", compile=False)
    assert sol.success
    torch.testing.assert_close(sol.x[0, -1], ref.x[0, -1], rtol=0, atol=1e-7)
    _, z = bowl.kkt_solve(sol.x[0, -1:, :3], sol.x[0, -1:, 3:])
    torch.testing.assert_close(sol.z[0, -1], z[0].detach(), rtol=0, atol=1e-7)
