"""A worked simulation scenario for every plant of the zoo.

A :class:`Scenario` names a plant, an initial state (consistent with the constraints of
constrained plants), a time span on which the solution is smooth and well defined, an input
where the plant takes one, and one physical parameter to differentiate. :func:`scenarios` lists
one for every plant class exported by :mod:`sysid.zoo`; the correctness tests run every
scenario through every integrator and driver, so a new plant is covered once it has a scenario
here. Index-1 DAE forms of the plants (semi-explicit, notes eq. 5.16; the index-1 KKT form of
constrained mechanics, eq. 2.168 with Baumgarte stabilisation, eq. 2.186) are listed by
:func:`dae_scenarios`, and the DAEs whose given form has index > 1 (which ``daeint`` must
refuse) by :func:`refused_scenarios`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import nn

from integrators.problems import ImplicitDAE, ImplicitODE, SemiExplicitDAE

from . import dae, mechanical, ode


def smooth_input(t: torch.Tensor) -> torch.Tensor:
    """u(t) = 0.5 sin(2 t): (1,) for a 0-dim t, (*batch, 1) for t of shape (*batch, 1)."""
    u = 0.5 * torch.sin(2 * t)
    return u if u.dim() else u.reshape(1)


@dataclass(frozen=True)
class Scenario:
    """One simulation of one plant.

    Attributes:
        name: the plant's class name (with a suffix where a class has several scenarios).
        plant_class: the zoo class the scenario covers.
        build: a fresh plant, ``build() -> nn.Module`` with ``forward(t, x, u=None)``.
        x0: (nx,) initial state, consistent with the constraints of constrained plants.
        t_end: end of the time span [0, t_end] (s).
        param: name of a parameter of the plant to differentiate, or None (then the
            gradient is taken with respect to ``x0``).
        u: the input ``u(t)`` (:func:`smooth_input`) for plants that take one, else None.
        stiff: explicit methods need impractically small steps (only implicit methods run).
        substeps: fixed steps per output interval (of ``t_end / 10``) that resolve the
            plant's fastest motion to about 1e-5 with a fourth-order method.
    """

    name: str
    plant_class: type
    build: Callable[[], nn.Module]
    x0: tuple[float, ...]
    t_end: float
    param: str | None
    u: Callable[[torch.Tensor], torch.Tensor] | None = None
    stiff: bool = False
    substeps: int = 5


@dataclass(frozen=True)
class DAEScenario:
    """One index-1 DAE simulation.

    Attributes:
        name, plant_class, t_end, param, u: as in :class:`Scenario`.
        build: a fresh plant, ``build() -> nn.Module``.
        problem: ``problem(plant)`` -> a :class:`SemiExplicitDAE` or :class:`ImplicitDAE`.
        x0: (nx,) initial differential states.
        z0: (nz,) guess of the initial algebraic states (``daeint`` makes it consistent).
        substeps: as in :class:`Scenario`.
    """

    name: str
    plant_class: type
    build: Callable[[], nn.Module]
    problem: Callable[[nn.Module], object]
    x0: tuple[float, ...]
    z0: tuple[float, ...]
    t_end: float
    param: str | None
    u: Callable[[torch.Tensor], torch.Tensor] | None = None
    substeps: int = 5


def _chain_rest(n_masses: int) -> tuple[float, ...]:
    """Masses of the hanging chain spread on the line between its ends, sagging by 0.1 m."""
    q = []
    for k in range(1, n_masses + 1):
        s = k / (n_masses + 1)
        q += [s, 0.0, -0.4 * s * (1 - s)]
    return tuple(q) + (0.0,) * (3 * n_masses)


def _two_pendulum_cartesian(theta1: float, theta2: float, length: float = 1.0):
    """q = (x, p1, p2) of the two-pendulum crane (vertical axes down) at angles theta1,
    theta2 from the vertical, at rest."""
    p1 = (length * math.sin(theta1), length * math.cos(theta1))
    p2 = (p1[0] + length * math.sin(theta2), p1[1] + length * math.cos(theta2))
    return (0.0, *p1, *p2) + (0.0,) * 5


def scenarios() -> list[Scenario]:
    """A scenario for every explicit-ODE plant of the zoo (mechanical plants in their explicit
    form eq. 2.42; singularly perturbed plants as stiff ODEs)."""
    sin_half, cos_half = math.sin(0.5), math.cos(0.5)
    return [
        Scenario("VanDerPol", ode.VanDerPol, ode.VanDerPol, (0.0, 2.0), 2.0, "mu", smooth_input),
        Scenario(
            "StiffVanDerPol",
            ode.StiffVanDerPol,
            lambda: ode.StiffVanDerPol(eps=1e-3),
            (2.0, -2.0 / 3.0),
            0.5,
            "eps",
            stiff=True,
            substeps=20,
        ),
        Scenario("Lorenz", ode.Lorenz, ode.Lorenz, (1.0, 1.0, 1.0), 0.5, "rho"),
        Scenario(
            "StiffLinear",
            ode.StiffLinear,
            lambda: ode.StiffLinear(eps=1e-2),
            (1.0, 0.0, 0.5, -0.5),
            0.5,
            "eps",
            stiff=True,
            substeps=25,
        ),
        Scenario(
            "LinearTestEquation",
            ode.LinearTestEquation,
            ode.LinearTestEquation,
            (1.0, -2.0),
            1.0,
            "lam",
        ),
        Scenario("Quadratic", ode.Quadratic, ode.Quadratic, (0.5,), 1.0, None),
        Scenario("SqrtAbs", ode.SqrtAbs, ode.SqrtAbs, (1.0,), 1.0, None),
        Scenario(
            "NonlinearExample",
            ode.NonlinearExample,
            ode.NonlinearExample,
            (0.5, 0.0),
            2.0,
            None,
            smooth_input,
        ),
        Scenario(
            "TwoMassSystem",
            dae.TwoMassSystem,
            lambda: dae.TwoMassSystem(m1=0.1, K=20.0),
            (0.1, 0.0, 0.0, 0.0),
            0.5,
            "rho",
            smooth_input,
        ),
        Scenario(
            "SingularlyPerturbedLinear",
            dae.SingularlyPerturbedLinear,
            dae.SingularlyPerturbedLinear,
            (1.0, 0.0),
            1.0,
            "a",
            smooth_input,
            stiff=True,
        ),
        Scenario(
            "SpringMass",
            mechanical.SpringMass,
            mechanical.SpringMass,
            (1.5, 0.0),
            0.5,
            "k",
            smooth_input,
        ),
        Scenario(
            "SpringMassDamper",
            mechanical.SpringMassDamper,
            mechanical.SpringMassDamper,
            (1.0, 0.0),
            2.0,
            "xi",
            smooth_input,
        ),
        Scenario(
            "Crane",
            mechanical.Crane,
            mechanical.Crane,
            (0.0, 0.5, 0.2, 0.0),
            0.5,
            "m",
            smooth_input,
        ),
        Scenario(
            "ElasticCranePolar",
            mechanical.ElasticCranePolar,
            mechanical.ElasticCranePolar,
            (0.0, 0.5, 1.1, 0.0, 0.0, 0.0),
            0.5,
            "K",
            smooth_input,
        ),
        Scenario(
            "ElasticCraneCartesian",
            mechanical.ElasticCraneCartesian,
            mechanical.ElasticCraneCartesian,
            (0.0, 1.1 * sin_half, 1.1 * cos_half, 0.0, 0.0, 0.0),
            0.5,
            "K",
            smooth_input,
        ),
        Scenario(
            "RigidCraneCartesian",
            mechanical.RigidCraneCartesian,
            lambda: mechanical.RigidCraneCartesian(baumgarte=5.0),
            (0.0, sin_half, cos_half, 0.3, 0.3, 0.0),
            0.5,
            "m",
            smooth_input,
        ),
        Scenario(
            "TwoPendulumCranePolar",
            mechanical.TwoPendulumCranePolar,
            mechanical.TwoPendulumCranePolar,
            (0.0, 0.4, -0.3, 0.0, 0.0, 0.0),
            0.5,
            "L",
            smooth_input,
        ),
        Scenario(
            "TwoPendulumCraneCartesian",
            mechanical.TwoPendulumCraneCartesian,
            lambda: mechanical.TwoPendulumCraneCartesian(baumgarte=5.0),
            _two_pendulum_cartesian(0.4, -0.3),
            0.5,
            "g",
            smooth_input,
        ),
        Scenario(
            "HangingChain",
            mechanical.HangingChain,
            lambda: mechanical.HangingChain(n_masses=3, m=0.2, K=5.0),
            _chain_rest(3),
            0.5,
            "K",
        ),
        Scenario(
            "Bowl",
            mechanical.Bowl,
            lambda: mechanical.Bowl(baumgarte=5.0),
            (1.0, 0.0, 0.25, 0.0, 1.0, 0.0),
            0.5,
            "g",
        ),
        Scenario(
            "DistributedRod",
            mechanical.DistributedRod,
            mechanical.DistributedRod,
            (0.3, 0.0),
            0.5,
            "L",
            smooth_input,
        ),
    ]


def dae_scenarios() -> list[DAEScenario]:
    """Index-1 DAE forms of zoo plants: the DAE limits of the singularly perturbed plants
    (eq. 5.37, 5.44), the index-1 examples of chapter 5 (eq. 5.46 as a fully implicit DAE,
    eq. 5.81 and 5.88 with their index-reduced algebraic equations, eq. 5.86, 5.93), and
    constrained mechanics in the index-1 KKT form (eq. 2.168) with Baumgarte stabilisation
    (eq. 2.186)."""

    def spl_problem(p):
        return SemiExplicitDAE(p.f, p.g)

    def two_mass_problem(p):
        return SemiExplicitDAE(p.f_544, p.g_544)

    def e546_problem(p):
        return ImplicitDAE(p.residual)

    def e581_problem(p):
        return SemiExplicitDAE(p.f, p.reduced_g)

    def e588_problem(p):
        return SemiExplicitDAE(p.f, p.reduced_g)

    def kkt_problem(p):
        return SemiExplicitDAE(*p.index1_dae(baumgarte=5.0))

    sin_half, cos_half = math.sin(0.5), math.cos(0.5)
    bowl_x0 = (1.0, 0.0, 0.25, 0.0, 1.0, 0.0)
    crane_x0 = (0.0, sin_half, cos_half, 0.3, 0.3, 0.0)
    return [
        DAEScenario(
            "SingularlyPerturbedLinear",
            dae.SingularlyPerturbedLinear,
            dae.SingularlyPerturbedLinear,
            spl_problem,
            (1.0,),
            (0.5,),
            1.0,
            "a",
            smooth_input,
        ),
        DAEScenario(
            "TwoMassSystem",
            dae.TwoMassSystem,
            dae.TwoMassSystem,
            two_mass_problem,
            (0.2, 0.0),
            (0.1,),
            1.0,
            "K",
            smooth_input,
            substeps=20,
        ),
        DAEScenario(
            "LinearIndex1DAE",
            dae.LinearIndex1DAE,
            dae.LinearIndex1DAE,
            e546_problem,
            (0.0, 1.0),
            (-1.0,),
            1.0,
            None,
            smooth_input,
        ),
        DAEScenario(
            "LinearIndex2DAE",
            dae.LinearIndex2DAE,
            dae.LinearIndex2DAE,
            e581_problem,
            (1.0, 1.0),
            (1.0, 1.0),
            1.0,
            None,
        ),
        DAEScenario(
            "UnitSphereDAE",
            dae.UnitSphereDAE,
            dae.UnitSphereDAE,
            e588_problem,
            (0.6, 0.8),
            (0.0,),
            1.0,
            "A",
        ),
        DAEScenario(
            "RigidCraneCartesian",
            mechanical.RigidCraneCartesian,
            mechanical.RigidCraneCartesian,
            kkt_problem,
            crane_x0,
            (0.0,),
            1.0,
            "m",
            smooth_input,
        ),
        DAEScenario(
            "Bowl",
            mechanical.Bowl,
            mechanical.Bowl,
            kkt_problem,
            bowl_x0,
            (0.0,),
            1.0,
            "g",
        ),
    ]


@dataclass(frozen=True)
class RefusedScenario:
    """A DAE of the zoo in a form of index > 1, which ``daeint`` must refuse.

    Attributes:
        name: a label; plant_class: the zoo class.
        setup: ``setup() -> (problem, x0, z0)`` handed to ``daeint``.
    """

    name: str
    plant_class: type
    setup: Callable[[], tuple]


def _index3_linear():
    plant = dae.LinearIndex3DAE()
    x0 = torch.tensor([1.0, 0.0], dtype=torch.float64)
    return ImplicitDAE(plant.residual), x0, torch.zeros(1, dtype=torch.float64)


def _no_algebraic_states(plant_class):
    """Eq. (5.2) / (5.3) as F(t, x', x) = 0: dF/dx' is singular (eq. 5.9, 5.11)."""

    def setup():
        plant = plant_class()

        def residual(t, xdot, x, u=None):
            return plant.residual(t, xdot, x, x[..., :0], u)

        return ImplicitODE(residual), torch.tensor([1.0, 3.0], dtype=torch.float64), None

    return setup


def _index2_semi_explicit(plant_class, x0, z0):
    def setup():
        plant = plant_class()
        problem = SemiExplicitDAE(plant.f, plant.g)
        return problem, torch.tensor(x0, dtype=torch.float64), torch.tensor(z0, dtype=torch.float64)

    return setup


def refused_scenarios() -> list[RefusedScenario]:
    """The zoo's DAEs whose given form has index > 1 (eq. 5.2, 5.3, 5.48, 5.81, 5.88): the
    index check (Theorem 9) must refuse them with ``HighIndexError``."""
    return [
        RefusedScenario(
            "AlgebraicStateDAE", dae.AlgebraicStateDAE, _no_algebraic_states(dae.AlgebraicStateDAE)
        ),
        RefusedScenario(
            "SingularMassMatrixDAE",
            dae.SingularMassMatrixDAE,
            _no_algebraic_states(dae.SingularMassMatrixDAE),
        ),
        RefusedScenario("LinearIndex3DAE", dae.LinearIndex3DAE, _index3_linear),
        RefusedScenario(
            "LinearIndex2DAE",
            dae.LinearIndex2DAE,
            _index2_semi_explicit(dae.LinearIndex2DAE, (1.0, 1.0), (0.0, 1.0)),
        ),
        RefusedScenario(
            "UnitSphereDAE",
            dae.UnitSphereDAE,
            _index2_semi_explicit(dae.UnitSphereDAE, (0.6, 0.8), (0.0,)),
        ),
    ]
