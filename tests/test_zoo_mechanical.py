"""Mechanical plants: the autograd builder against the notes' closed forms (chapter 2).

Typos of the notes found by these comparisons (fixed in the closed forms of
sysid/zoo/mechanical.py, see each plant's docstring):
- eq. (2.105): W(2,1) printed 2 L cos(theta2) (a transposed entry; W must be symmetric and
  W(1,2) = 2 L cos(theta1)); W(2,3) = W(3,2) need L^2 cos(theta1 - theta2), not L cos(...);
- eq. (2.108): the convective term has the wrong overall sign;
- eq. (2.95c)-(2.97): gravity enters with +m g in grad L and the spring terms of eq. (2.96),
  (2.97) have the wrong sign: qddot_k = K/m (p_{k-1} - p_k) + K/m (p_{k+1} - p_k) - g e_z;
- eq. (2.88): "- m g p2" in L should be "+ m g p2" (eq. 2.89c, 2.90 are right);
- eq. (2.173): right-hand side is (0, 0, -m g, (p1dot^2 + p2dot^2)/2): sign of gravity and a
  missing factor 1/2;
- eq. (2.178): M(q) = [[W, a^T], [a, 0]] with a = (x - p1, p1 - x, p2) and the last entry of
  the right-hand side is -(xdot^2 + p1dot^2 + p2dot^2 - 2 xdot p1dot);
- eq. (2.19)-(2.20): kinetic energy of the rod misses the 1/2: W = m L^2 / 3, not 2/3 m L^2.
Checked and right as printed: eq. (2.60), (2.70), (2.76), (2.80), (2.90), (2.107c), (2.174).
"""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from integrators import odeint
from sysid.zoo import (
    Bowl,
    Crane,
    DistributedRod,
    ElasticCraneCartesian,
    ElasticCranePolar,
    HangingChain,
    RigidCraneCartesian,
    SpringMass,
    SpringMassDamper,
    TwoPendulumCraneCartesian,
    TwoPendulumCranePolar,
)

DT = torch.float64
UNCONSTRAINED = [
    SpringMass,
    SpringMassDamper,
    Crane,
    ElasticCranePolar,
    ElasticCraneCartesian,
    TwoPendulumCranePolar,
    lambda: HangingChain(n_masses=6, m=0.2, K=5.0),
    DistributedRod,
]
CONSTRAINED = [RigidCraneCartesian, TwoPendulumCraneCartesian, Bowl]


def _states(plant, n, seed):
    gen = torch.Generator().manual_seed(seed)
    q = torch.randn(n, plant.nq, dtype=DT, generator=gen)
    qd = torch.randn(n, plant.nq, dtype=DT, generator=gen)
    u = torch.randn(n, 1, dtype=DT, generator=gen)
    if isinstance(plant, ElasticCranePolar):
        q[:, 2] = q[:, 2].abs() + 0.5  # rod length > 0
    return q, qd, u


@pytest.mark.parametrize("make", UNCONSTRAINED)
def test_builder_accelerations_equal_closed_forms(make):
    plant = make()
    q, qd, u = _states(plant, 16, 0)
    acc = plant.accelerations(q, qd, u if plant.nu else None)
    ref = plant.closed_form_acceleration(q, qd, u if plant.nu else None)
    torch.testing.assert_close(acc, ref, rtol=1e-10, atol=1e-10)


@settings(max_examples=20, deadline=None)
@given(
    st.floats(0.2, 5.0),
    st.floats(0.1, 3.0),
    st.floats(0.3, 3.0),
    st.floats(-3.0, 3.0),
    st.floats(-5.0, 5.0),
)
def test_crane_eq_2_70_over_parameters(M, m, L, theta, thetadot):
    plant = Crane(M=M, m=m, L=L)
    q = torch.tensor([[0.3, theta]], dtype=DT)
    qd = torch.tensor([[-1.0, thetadot]], dtype=DT)
    torch.testing.assert_close(
        plant.accelerations(q, qd), plant.closed_form_acceleration(q, qd), rtol=1e-10, atol=1e-10
    )


@pytest.mark.parametrize("make", CONSTRAINED)
def test_kkt_accelerations_and_multipliers_equal_closed_forms(make):
    plant = make()
    q, qd, u = _states(plant, 16, 1)
    u = u if plant.nu else None
    acc, z = plant.kkt_solve(q, qd, u)
    acc_ref, z_ref = plant.closed_form_acceleration(q, qd, u)
    torch.testing.assert_close(acc, acc_ref, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(z, z_ref, rtol=1e-10, atol=1e-10)
    kkt_ref, _ = plant.closed_form_kkt(q, qd, u)
    torch.testing.assert_close(plant.kkt_matrix(q), kkt_ref, rtol=1e-12, atol=1e-12)


def test_bowl_kkt_determinant_eq_2_174():
    plant = Bowl(m=1.7)
    q, _, _ = _states(plant, 32, 2)
    det = torch.linalg.det(plant.kkt_matrix(q))
    torch.testing.assert_close(det, plant.closed_form_kkt_determinant(q), rtol=1e-12, atol=0)
    assert bool((det < 0).all())


@pytest.mark.parametrize("make", UNCONSTRAINED + CONSTRAINED)
def test_mass_matrix_symmetric_positive_definite(make):
    plant = make()
    q, qd, _ = _states(plant, 8, 3)
    w = plant.mass_matrix(q, qd)
    torch.testing.assert_close(w, w.transpose(-1, -2), rtol=0, atol=1e-13)
    assert bool((torch.linalg.eigvalsh(w) > 0).all())
    if hasattr(plant, "closed_form_mass_matrix"):
        torch.testing.assert_close(w, plant.closed_form_mass_matrix(q), rtol=1e-12, atol=1e-12)


def test_rod_quadrature_gives_mass_matrix_one_third_m_l_squared():
    """Eq. (2.19)-(2.20) with the 1/2 fixed: W = m L^2 / 3 for any number of nodes >= 2."""
    for nodes in (2, 5):
        plant = DistributedRod(m=2.0, L=1.5, n_nodes=nodes)
        w = plant.mass_matrix(torch.tensor([[0.4]], dtype=DT))
        torch.testing.assert_close(w[0, 0, 0], torch.tensor(2.0 * 1.5**2 / 3, dtype=DT))
        v = plant.potential_energy(torch.tensor([[0.4]], dtype=DT))
        ref = 0.5 * 2.0 * 9.81 * 1.5 * torch.sin(torch.tensor(0.4, dtype=DT))  # eq. (2.24)
        torch.testing.assert_close(v[0], ref)


def _energy_drift(plant, x0, dt, t_end):
    t = torch.arange(0, t_end + dt / 2, dt, dtype=DT)
    sol = odeint(plant, x0, t, method="rk4", compile=False)
    n = plant.nq
    e = plant.energy(sol.x[..., :n], sol.x[..., n:])
    return (e - e[..., :1]).abs().amax()


@pytest.mark.parametrize(
    "make", [Crane, ElasticCraneCartesian, TwoPendulumCranePolar, lambda: HangingChain(4)]
)
def test_energy_conserved_to_rk4_accuracy(make):
    """Unforced undamped plants conserve T + V; the RK4 drift shrinks like dt^4."""
    plant = make()
    q, qd, _ = _states(plant, 2, 4)
    x0 = torch.cat([0.3 * q, 0.3 * qd], -1)
    coarse = _energy_drift(plant, x0, 0.02, 0.4)
    fine = _energy_drift(plant, x0, 0.01, 0.4)
    scale = plant.energy(x0[..., : plant.nq], x0[..., plant.nq :]).abs().max()
    assert fine < 1e-5 * scale
    assert coarse / fine > 10.0  # order 4 -> ratio 16


def test_plant_parameters_receive_gradients_matching_finite_differences():
    q = torch.tensor([[0.1, 0.7]], dtype=DT)
    qd = torch.tensor([[0.5, -0.3]], dtype=DT)
    plant = Crane(M=1.3, m=0.4, L=0.9)
    plant.accelerations(q, qd)[0, 1].backward()
    h = 1e-6
    with torch.no_grad():
        fd = (
            Crane(M=1.3, m=0.4, L=0.9 + h).accelerations(q, qd)[0, 1]
            - Crane(M=1.3, m=0.4, L=0.9 - h).accelerations(q, qd)[0, 1]
        ) / (2 * h)
    assert plant.L.grad.item() == pytest.approx(float(fd), rel=1e-6)


def test_float32_states():
    plant = Crane()
    q, qd, u = _states(plant, 4, 5)
    acc = plant.accelerations(q.float(), qd.float(), u.float())
    assert acc.dtype == torch.float32
    torch.testing.assert_close(
        acc.double(), plant.closed_form_acceleration(q, qd, u), rtol=1e-4, atol=1e-4
    )


def test_per_sample_parameters_give_each_sample_its_own_plant():
    """Parameters of shape (B, 1) are B plants: the builder's accelerations must equal the
    closed form of eq. 1.28 / 2.53 sample by sample (a (B, 1) x (B,) broadcast once summed
    the spring forces of the whole batch)."""
    from sysid.zoo import SpringMass, SpringMassDamper

    gen = torch.Generator().manual_seed(3)
    B = 5
    x = torch.randn(B, 2, generator=gen, dtype=torch.float64)
    u = torch.randn(B, 1, generator=gen, dtype=torch.float64)
    m = 0.5 + torch.rand(B, 1, generator=gen, dtype=torch.float64)
    k = 1.0 + torch.rand(B, 1, generator=gen, dtype=torch.float64)
    xi = torch.rand(B, 1, generator=gen, dtype=torch.float64)
    smd = SpringMassDamper(m=m, xi=xi, K=k)
    expected = (u - xi * x[:, 1:] - k * x[:, :1]) / m  # eq. 1.28 per sample
    torch.testing.assert_close(smd(torch.tensor(0.0), x, u)[:, 1:], expected, rtol=1e-12, atol=0)
    sm = SpringMass(m=m, k=k)
    expected = 9.81 - k / m * x[:, :1] + u / m  # eq. 2.53 per sample
    torch.testing.assert_close(sm(torch.tensor(0.0), x, u)[:, 1:], expected, rtol=1e-12, atol=0)


@pytest.mark.parametrize("make", [m for m in UNCONSTRAINED + CONSTRAINED if m().nu])
def test_input_shared_by_the_batch_equals_per_sample_inputs(make):
    """u sampled as (T, nu), shared by a batch of states, is broadcast: the same solution as
    the (B, T, nu) copy and as each sample on its own. (Crane-type plants with point forces
    and TwoPendulumCraneCartesian's generalized force used to fail on a shared input.)"""
    plant = make()
    q, qd, _ = _states(plant, 3, seed=4)
    x0 = torch.cat([q, qd], -1) * 0.3
    t = torch.linspace(0, 0.2, 5, dtype=DT)
    u = torch.sin(3 * t)[:, None].repeat(1, plant.nu)
    shared = odeint(plant, x0, t, method="rk4", u=u).x
    copied = odeint(plant, x0, t, method="rk4", u=u.expand(3, *u.shape)).x
    alone = torch.stack([odeint(plant, x0[i], t, method="rk4", u=u).x for i in range(3)])
    torch.testing.assert_close(shared, copied, rtol=1e-14, atol=1e-14)
    torch.testing.assert_close(shared, alone, rtol=1e-14, atol=1e-14)
