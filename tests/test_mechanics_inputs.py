"""LagrangianSystem on unusual but valid inputs, and its errors on invalid ones.

Affine position maps and linear constraints (derivatives that autograd sees as unconnected),
state / input widths, non-positive masses, and batches with a member whose mass matrix is
singular (NaN for that member only, NON_FINITE in the integrators).
"""

import math
import re

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from integrators import odeint
from integrators.errors import InputValidationError, RKIdentWarning
from integrators.solution import Status
from sysid.mechanics import LagrangianSystem
from sysid.zoo import Bowl, Crane, RigidCraneCartesian, SpringMass

DT = torch.float64
G = 9.81
METHODS = [
    ("rk4", {"compile": False}),
    ("radau_iia", {"rtol": 1e-10, "atol": 1e-10}),
    ("dopri5", {"rtol": 1e-10, "atol": 1e-10}),
]


def _free_particle(mass=2.0):
    """A point mass in the plane in Cartesian coordinates q = p, gravity along -y."""
    return LagrangianSystem(
        2,
        point_masses=torch.tensor([mass], dtype=DT),
        positions=lambda q: q.unsqueeze(-2),
        gravity=torch.tensor([0.0, -G], dtype=DT),
    )


@pytest.mark.parametrize(("method", "options"), METHODS)
def test_free_particle_in_gravity_is_the_parabola(method, options):
    """Positions p = q (Jacobian independent of q): q(t) = q0 + v0 t + g t^2 / 2."""
    plant = _free_particle()
    x0 = torch.tensor([[0.0, 1.0, 2.0, 3.0], [-1.0, 0.5, -0.5, 0.0]], dtype=DT)
    t = torch.linspace(0.0, 1.0, 11, dtype=DT)
    with torch.no_grad():
        sol = odeint(plant, x0, t, method=method, **options)
    assert sol.success, sol.messages
    g = torch.tensor([0.0, -G], dtype=DT)
    tt = t[:, None]
    q = x0[:, None, :2] + x0[:, None, 2:] * tt + 0.5 * g * tt**2
    v = x0[:, None, 2:] + g * tt
    torch.testing.assert_close(sol.x, torch.cat([q, v], -1), rtol=0, atol=1e-9)


@pytest.mark.parametrize(("method", "options"), METHODS)
def test_spring_particle_on_an_affine_map_is_the_cosine(method, options):
    """p = 2 q + 1 (affine), V = k/2 (p - 1)^2: 4 m qddot = -4 k q, so q oscillates with
    omega = sqrt(k / m) (the factor 2 of the Jacobian cancels; a wrong W changes omega)."""
    m, k = 0.5, 8.0
    plant = LagrangianSystem(
        1,
        point_masses=torch.tensor([m], dtype=DT),
        positions=lambda q: (2.0 * q + 1.0).unsqueeze(-1),
        potential=lambda q: 0.5 * k * (2.0 * q[..., 0]) ** 2,
    )
    x0 = torch.tensor([[0.3, 0.0], [0.0, 1.0], [-0.2, 0.5]], dtype=DT)
    t = torch.linspace(0.0, 2.0, 21, dtype=DT)
    opts = {**options, "substeps": 40} if method == "rk4" else options
    with torch.no_grad():
        sol = odeint(plant, x0, t, method=method, **opts)
    assert sol.success, sol.messages
    w = math.sqrt(k / m)
    q0, v0, tt = x0[:, None, :1], x0[:, None, 1:], t[:, None]
    q = q0 * torch.cos(w * tt) + v0 / w * torch.sin(w * tt)
    v = -q0 * w * torch.sin(w * tt) + v0 * torch.cos(w * tt)
    torch.testing.assert_close(sol.x, torch.cat([q, v], -1), rtol=0, atol=1e-7)


def test_linear_constraint_and_q_free_kinetic_energy():
    """c(q) = q0 - q1 (constant gradient): sliding down a 45 degree line, qddot = -g/2 on
    both axes and z = m g / 2 (W qddot + a^T z = Q with a = (1, -1)). A kinetic energy
    without q and no potential: qddot = F / m."""
    m = 1.5
    incline = LagrangianSystem(
        2,
        diagonal_mass=torch.tensor([m, m], dtype=DT),
        potential=lambda q: m * G * q[..., 1],
        constraints=lambda q: (q[..., 0] - q[..., 1]).unsqueeze(-1),
    )
    q = torch.tensor([[0.3, 0.3], [-1.0, -1.0]], dtype=DT)
    qd = torch.tensor([[0.5, 0.5], [0.0, 0.0]], dtype=DT)
    qdd, z = incline.kkt_solve(q, qd)
    torch.testing.assert_close(qdd, torch.full_like(qdd, -G / 2), rtol=1e-14, atol=1e-14)
    torch.testing.assert_close(z, torch.full_like(z, m * G / 2), rtol=1e-14, atol=1e-14)
    c, cdot = incline.drift(torch.cat([q, qd], -1))
    assert torch.equal(c, torch.zeros_like(c)) and torch.equal(cdot, torch.zeros_like(cdot))

    pushed = LagrangianSystem(
        1,
        nu=1,
        kinetic_energy=lambda q, qd: 0.5 * m * qd[..., 0] ** 2,
        generalized_force=lambda q, qd, u: u,
    )
    u = torch.tensor([[3.0], [-1.5]], dtype=DT)
    torch.testing.assert_close(pushed.accelerations(q[:, :1], qd[:, :1], u), u / m)


def test_float32_state_with_float32_tensors_in_the_constraint():
    """The constraint callable captures a float32 tensor: forward on a float32 state must not
    probe it with float64 (incline of the previous test: qddot = -g/2, z = m g/2)."""
    a = torch.tensor([[1.0], [-1.0]])
    incline = LagrangianSystem(
        2,
        diagonal_mass=torch.ones(2),
        potential=lambda q: G * q[..., 1],
        constraints=lambda q: q @ a,
    )
    assert incline.is_constrained
    x = torch.tensor([[0.2, 0.2, 1.0, 1.0]])
    out = incline(0.0, x)
    assert out.dtype == torch.float32
    torch.testing.assert_close(out, torch.tensor([[1.0, 1.0, -G / 2, -G / 2]]))


def test_affine_positions_gradient_matches_finite_differences():
    """Gradient of the acceleration w.r.t. a mass parameter through the affine-position path
    (grad mode with a parameter): W = 4 m, qddot = -k q / m."""
    k = 8.0
    mass = torch.nn.Parameter(torch.tensor([0.5], dtype=DT))
    plant = LagrangianSystem(
        1,
        point_masses=lambda: mass,
        positions=lambda q: (2.0 * q + 1.0).unsqueeze(-1),
        potential=lambda q: 0.5 * k * (2.0 * q[..., 0]) ** 2,
    )
    q = torch.tensor([[0.3]], dtype=DT)
    acc = plant.accelerations(q, torch.zeros_like(q))
    (grad,) = torch.autograd.grad(acc.sum(), mass)
    torch.testing.assert_close(grad, torch.tensor([k * 0.3 / 0.5**2], dtype=DT))


@given(
    batch=st.sampled_from([(), (1,), (3,), (2, 3)]),
    dtype=st.sampled_from([torch.float32, torch.float64]),
    seed=st.integers(0, 2**16),
)
@settings(max_examples=15, deadline=None)
def test_affine_particle_any_batch_shape_and_dtype(batch, dtype, seed):
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(*batch, 4, dtype=DT, generator=gen).to(dtype)
    out = _free_particle()(0.0, x)
    assert out.shape == x.shape and out.dtype == dtype
    ref = torch.cat([x[..., 2:], torch.tensor([0.0, -G], dtype=dtype).expand(*batch, 2)], -1)
    torch.testing.assert_close(out, ref)


# ---------------------------------------------------------------------------- argument checks
@pytest.mark.parametrize("width", [3, 5, 1])
def test_state_of_the_wrong_width_is_rejected(width):
    plant = _free_particle()
    x = torch.zeros(3, width, dtype=DT)
    with pytest.raises(InputValidationError, match=rf"2 nq\) = \(\*batch, 4\), got \(3, {width}\)"):
        plant(0.0, x)
    with pytest.raises(InputValidationError, match=r"\(\*batch, 4\)"):
        odeint(plant, x, torch.linspace(0.0, 1.0, 3, dtype=DT), method="rk4", compile=False)
    with pytest.raises(InputValidationError, match=r"implicit_residual.*\(\*batch, 4\)"):
        plant.implicit_residual(0.0, torch.zeros(3, 4, dtype=DT), x)
    with pytest.raises(InputValidationError, match=r"q must have shape \(\*batch, nq\)"):
        plant.accelerations(torch.zeros(3, width, dtype=DT), torch.zeros(3, 2, dtype=DT))


def test_input_of_the_wrong_width_is_rejected():
    crane = Crane()
    x = torch.zeros(2, 4, dtype=DT)
    with pytest.raises(InputValidationError, match=r"u must have shape \(\*batch, nu\) .*1\).*2\)"):
        crane(0.0, x, torch.ones(2, 2, dtype=DT))


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan")])
def test_non_positive_masses_are_rejected_at_construction(bad):
    with pytest.raises(InputValidationError, match=r"diagonal_mass must be finite and > 0"):
        LagrangianSystem(2, diagonal_mass=torch.tensor([1.0, bad], dtype=DT))
    with pytest.raises(InputValidationError, match=r"point_masses must be finite and > 0.*\[1\]"):
        LagrangianSystem(2, point_masses=[1.0, bad], positions=lambda q: torch.stack([q, q], -2))
    for make in (
        lambda: Crane(m=bad),
        lambda: Crane(M=bad),
        lambda: Crane(L=bad),
        lambda: SpringMass(m=bad),
        lambda: Bowl(m=bad),
    ):
        with pytest.raises(InputValidationError, match=r"must be (finite|> 0)"):
            make()


def test_point_mass_count_must_match_positions():
    plant = LagrangianSystem(
        2, point_masses=torch.tensor([1.0], dtype=DT), positions=lambda q: torch.stack([q, q], -2)
    )
    q = torch.zeros(3, 2, dtype=DT)
    with pytest.raises(InputValidationError, match=r"gives 2 points"):
        plant.kinetic_energy(q, q)
    with pytest.raises(InputValidationError, match=r"gives 2 points"):
        plant.accelerations(q, q)


# ---------------------------------------------------------------------------- singular members
def _lever(mass):
    """A slider q0 pushed by a constant force 1 along +q0, carrying a point at height
    min(q0, 0) q1 held by a spring on q1: W(q) = m [[1 + q1^2, q0 q1], [q0 q1, q0^2]] for
    q0 < 0, singular wherever q0 >= 0 (the lever arm vanishes)."""
    return LagrangianSystem(
        2,
        point_masses=mass,
        positions=lambda q: torch.stack(
            [q[..., 0], torch.clamp(q[..., 0], max=0.0) * q[..., 1]], -1
        ).unsqueeze(-2),
        potential=lambda q: -q[..., 0] + 2.0 * q[..., 1] ** 2,
    )


# members 0 and 2 stay in q0 < 0; member 1 (q1 = q1dot = 0, so q0 = -0.3 + 0.5 t + t^2 / 2)
# reaches q0 = 0 at t = (sqrt(3.4) - 1) / 2 = 0.42 and stays there
X0 = torch.tensor([[-2.0, 0.2, -1.0, 0.0], [-0.3, 0.0, 0.5, 0.0], [-1.5, -0.1, 0.0, 0.3]], dtype=DT)
T_HIT = (math.sqrt(3.4) - 1) / 2


@pytest.mark.parametrize(("method", "options"), METHODS)
def test_singular_mass_matrix_in_one_member_leaves_the_others(method, options):
    plant = _lever(torch.tensor([1.0], dtype=DT))
    t = torch.linspace(0.0, 1.0, 11, dtype=DT)
    with torch.no_grad(), pytest.warns(RKIdentWarning, match=r"W\(q\) is singular") as record:
        sol = odeint(plant, X0, t, method=method, **options)
    # the batch index names the member, or (member, stage) where an implicit method evaluates
    # the stages together; member 1 is named
    messages = [str(w.message) for w in record]
    assert any(re.search(r"batch index \[(1\]|.*\(1, \d+\))", m) for m in messages), messages
    with torch.no_grad():
        alone = [odeint(plant, X0[i : i + 1], t, method=method, **options) for i in (0, 2)]
    for i, ref in zip((0, 2), alone, strict=True):
        assert ref.success
        torch.testing.assert_close(sol.x[i], ref.x[0], rtol=1e-12, atol=1e-12)
    assert sol.status.tolist() == [Status.SUCCESS, Status.NON_FINITE, Status.SUCCESS]
    assert len(sol.messages) == 1 and re.match(r"sample (1|\(1,\)):", sol.messages[0])
    assert "NON_FINITE" in sol.messages[0] or "non-finite" in sol.messages[0]
    before = t < T_HIT  # the bad member is exact up to its failure (uniform acceleration)
    q0 = -0.3 + 0.5 * t[before] + 0.5 * t[before] ** 2
    torch.testing.assert_close(sol.x[1, before, 0], q0, rtol=0, atol=1e-9)


@pytest.mark.parametrize(("method", "options"), METHODS)
def test_singular_member_outputs_are_nan_after_the_failure(method, options):
    plant = _lever(torch.tensor([1.0], dtype=DT))
    t = torch.linspace(0.0, 1.0, 11, dtype=DT)
    with torch.no_grad(), pytest.warns(RKIdentWarning):
        sol = odeint(plant, X0, t, method=method, **options)
    assert torch.isnan(sol.x[1, t > T_HIT]).all()


def test_singular_member_gives_nan_and_finite_gradients_for_the_others():
    """A per-call batch: the singular member is NaN, the others equal their stand-alone
    accelerations, and the gradient of their sum w.r.t. the mass parameter is unaffected."""
    mass = torch.nn.Parameter(torch.tensor([1.3], dtype=DT))
    plant = _lever(lambda: mass)
    q, qd = X0[:, :2].clone(), X0[:, 2:]
    q[1, 0] = 0.0  # member 1 exactly where the lever vanishes
    with pytest.warns(RKIdentWarning, match=r"singular at batch index \[1\]"):
        acc = plant.accelerations(q, qd)
    assert torch.isnan(acc[1]).all()
    good = [0, 2]
    ref = plant.accelerations(q[good], qd[good])
    torch.testing.assert_close(acc[good], ref, rtol=1e-14, atol=1e-14)
    (g_batch,) = torch.autograd.grad(acc[good].sum(), mass)
    (g_ref,) = torch.autograd.grad(ref.sum(), mass)
    assert torch.isfinite(g_batch).all()
    torch.testing.assert_close(g_batch, g_ref, rtol=1e-14, atol=1e-14)
    # the plant is linear in 1/m: d(sum qddot)/dm = -sum qddot / m
    torch.testing.assert_close(g_ref, -ref.sum().reshape(1) / 1.3, rtol=1e-12, atol=1e-12)


def test_singular_kkt_matrix_in_one_member_gives_nan_for_it_only():
    """Rigid crane with the mass at the cart in member 1 (a = 0): NaN there; member 0 equals
    the closed form of eq. (2.178), for the Schur path (diagonal W) and the full KKT path."""
    plant = RigidCraneCartesian()
    q = torch.tensor([[0.0, 0.5, 1.0], [0.3, 0.3, 0.0]], dtype=DT)
    qd = torch.tensor([[0.1, -0.2, 0.1], [0.0, 0.0, 0.0]], dtype=DT)
    ref_qdd, ref_z = plant.closed_form_acceleration(q[:1], qd[:1])
    general = LagrangianSystem(
        3,
        point_masses=torch.tensor([1.0, 0.5], dtype=DT),
        positions=lambda q: torch.stack(
            [torch.stack([q[..., 0], torch.zeros_like(q[..., 0])], -1), q[..., 1:]], -2
        ),
        gravity=torch.tensor([0.0, G], dtype=DT),  # p2 points down
        constraints=plant.constraints,
    )
    for system, what in ((plant, "a W\\^-1 a\\^T"), (general, "KKT matrix")):
        with pytest.warns(RKIdentWarning, match=rf"{what}.* singular at batch index \[1\]"):
            qdd, z = system.kkt_solve(q, qd)
        assert torch.isnan(qdd[1]).all() and torch.isnan(z[1]).all()
        torch.testing.assert_close(qdd[:1], ref_qdd, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(z[:1], ref_z, rtol=1e-12, atol=1e-12)


def _cart_pole(m):
    """A cart-pole by its kinetic energy callable (the general autograd path, full W(q)):
    cart x, pole angle theta, pole mass ``m`` (a number or a (B, 1) tensor), horizontal force."""

    def kinetic(q, qd):
        mass = torch.as_tensor(m, dtype=DT)[..., 0] if torch.is_tensor(m) else m
        x_dot, th, th_dot = qd[..., 0], q[..., 1], qd[..., 1]
        return (
            0.5 * (1.0 + mass) * x_dot**2
            + mass * x_dot * th_dot * torch.cos(th)
            + (0.5 * mass * th_dot**2)
        )

    def potential(q):
        mass = torch.as_tensor(m, dtype=DT)[..., 0] if torch.is_tensor(m) else m
        return -mass * G * torch.cos(q[..., 1])

    return LagrangianSystem(
        2,
        nu=1,
        kinetic_energy=kinetic,
        potential=potential,
        generalized_force=lambda q, qd, u: torch.cat([u, torch.zeros_like(u)], -1),
    )


MEMBER_PLANTS = {
    "Crane (point masses)": (lambda m: Crane(m=m), 2),
    "cart-pole (kinetic energy)": (_cart_pole, 2),
    "RigidCraneCartesian (diagonal, constrained)": (lambda L: RigidCraneCartesian(L=L), 3),
}


@pytest.mark.parametrize("plant", MEMBER_PLANTS)
@pytest.mark.parametrize("batched_by", ["input", "parameter"])
def test_members_batched_by_inputs_or_parameters_from_one_state(plant, batched_by):
    """One state (nq,) with per-member inputs (B, nu) or a per-member parameter (B, 1): the
    dynamics of every member equal those of the member alone. (They did not: a full W(q)
    shared by the members was taken for a diagonal one when r had the same number of
    dimensions, and gradients of a batch of energies with respect to the one shared state
    summed over the members.)"""
    make, nq = MEMBER_PLANTS[plant]
    values = torch.tensor([[0.6], [0.9], [1.3]], dtype=DT)
    gen = torch.Generator().manual_seed(3)
    x = 0.3 * torch.randn(2 * nq, generator=gen, dtype=DT)
    if plant.startswith("Rigid"):  # a state on the constraint |p - (x, 0)| = L of member 0
        x = torch.tensor([0.1, 0.3, 0.5, 0.2, 0.0, 0.0], dtype=DT)
    u = torch.tensor([[1.0], [-2.0], [0.5]], dtype=DT)
    if batched_by == "input":
        batched = make(0.8).forward(0.0, x, u)
        alone = [make(0.8).forward(0.0, x, u[i]) for i in range(3)]
    else:
        batched = make(values).forward(0.0, x, u[0])
        alone = [make(float(values[i, 0])).forward(0.0, x, u[0]) for i in range(3)]
    torch.testing.assert_close(batched, torch.stack(alone), rtol=1e-12, atol=1e-12)


def test_checkpointed_run_of_a_lagrangian_plant_evaluates_it_once_per_stage():
    """odeint(..., checkpoint=True) on a Lagrangian plant with an input: the same states and
    parameter gradients as without checkpointing, and the plant called once per stage in the
    forward pass (its inner derivatives read tensors the checkpoint would otherwise drop and
    recompute: 601 calls instead of 25 for 6 RK4 steps)."""
    from sysid.zoo import Crane

    def run(checkpoint):
        plant = Crane().to(torch.float64)
        calls = []
        plant.register_forward_hook(lambda *args: calls.append(1))
        t = torch.linspace(0, 1.0, 7, dtype=torch.float64)
        x0 = torch.tensor([[0.0, 0.3, 0.0, 0.0]], dtype=torch.float64)
        u = torch.linspace(-1, 1, 7, dtype=torch.float64).reshape(1, 7, 1)
        sol = odeint(plant, x0, t, u=u, method="rk4", checkpoint=checkpoint)
        forward_calls = len(calls)
        grads = torch.autograd.grad(sol.x.sum(), list(plant.parameters()))
        return sol.x.detach(), grads, forward_calls

    x, grads, calls = run(True)
    x_plain, grads_plain, calls_plain = run(False)
    assert calls == calls_plain == 1 + 6 * 4  # the probe of f at t0, then 4 stages per step
    torch.testing.assert_close(x, x_plain, rtol=0, atol=0)
    for g, g_plain in zip(grads, grads_plain, strict=True):
        torch.testing.assert_close(g, g_plain, rtol=1e-14, atol=0)
