"""State order of every zoo plant: ``state_names`` and the first line of the class docstring."""

import re

import pytest
import torch

import sysid.zoo as zoo
from integrators.errors import InputValidationError
from sysid.mechanics import LagrangianSystem

DT = torch.float64


def _output_width(plant, names) -> int:
    """Width of the plant's state derivative (forward / f) or residual at a random state."""
    x = torch.rand(3, len(names), dtype=DT, generator=torch.Generator().manual_seed(0)) + 0.5
    z = torch.rand(3, getattr(plant, "nz", 0), dtype=DT)
    t = torch.zeros((), dtype=DT)
    if hasattr(plant, "residual"):  # F(t, xdot, x, z) = 0: nx + nz equations
        return plant.residual(t, torch.zeros_like(x), x, z).shape[-1] - plant.nz
    if type(plant).forward is not torch.nn.Module.forward:  # an ODE xdot = f(t, x)
        return plant(t, x).shape[-1]
    return plant.f(t, x, z).shape[-1]


@pytest.mark.parametrize("name", zoo.__all__)
def test_state_names_match_the_state_and_the_docstring(name):
    plant = getattr(zoo, name)()
    names = plant.state_names
    assert isinstance(names, tuple) and all(isinstance(n, str) and n for n in names)
    assert len(set(names)) == len(names) == plant.nx
    assert _output_width(plant, names) == len(names)
    if getattr(plant, "nz", 0):
        assert len(plant.algebraic_names) == plant.nz
    first = type(plant).__doc__.strip().splitlines()[0]
    assert "state" in first.lower(), first
    tail = first[first.lower().index("state") :]
    shown = names if len(names) <= 8 else names[:3]  # long states show their first names
    where = []
    for n in shown:
        match = re.search(rf"(?<![\w']){re.escape(n)}(?![\w'])", tail)
        assert match is not None, f"{name}: {n!r} missing from the first docstring line {first!r}"
        where.append(match.start())
    assert where == sorted(where), f"{name}: the first docstring line lists another order"


def test_van_der_pol_warns_of_its_velocity_position_order():
    first = zoo.VanDerPol.__doc__.splitlines()[0]
    assert first.index("velocity") < first.index("position")
    # x2' = x1: the second state is the position, the first its rate
    x = torch.tensor([0.7, -0.2], dtype=DT)
    assert zoo.VanDerPol()(torch.zeros(()), x)[1] == x[0]


def test_state_names_follow_construction():
    chain = zoo.HangingChain(n_masses=2)
    assert chain.state_names == (
        *("x1", "y1", "z1", "x2", "y2", "z2"),
        *("x1dot", "y1dot", "z1dot", "x2dot", "y2dot", "z2dot"),
    )
    assert zoo.UnitSphereDAE(A=torch.eye(3), b=torch.ones(3)).state_names == ("x1", "x2", "x3")
    assert zoo.LinearTestEquation(lam=[-1.0, -2.0]).state_names == ("x1", "x2")
    assert zoo.Crane().state_names == ("x", "theta", "xdot", "thetadot")


def test_lagrangian_system_names():
    plant = LagrangianSystem(2, diagonal_mass=torch.ones(2, dtype=DT))
    assert plant.state_names == ("q1", "q2", "q1dot", "q2dot") and plant.nx == 4
    named = LagrangianSystem(1, diagonal_mass=torch.ones(1, dtype=DT), coordinate_names=["s"])
    assert named.state_names == ("s", "sdot")
    with pytest.raises(InputValidationError, match="coordinate_names has 1 entries; need nq = 2"):
        LagrangianSystem(2, diagonal_mass=torch.ones(2, dtype=DT), coordinate_names=["s"])
