"""The exception and warning hierarchy shared by ``integrators`` and ``sysid``."""

import inspect

import pytest
import torch

import integrators
import integrators.errors
import sysid
import sysid.errors


def _defined_in(module) -> list[type]:
    """Exception and warning classes defined (not imported) in ``module``."""
    return [
        obj
        for _, obj in inspect.getmembers(module, inspect.isclass)
        if issubclass(obj, BaseException) and obj.__module__ == module.__name__
    ]


INTEGRATORS = _defined_in(integrators.errors)
SYSID = _defined_in(sysid.errors)
ALL = INTEGRATORS + SYSID


def _ids(cls):
    return cls.__name__


def test_the_hierarchy_holds_its_bases_and_the_named_classes():
    names = {c.__name__ for c in ALL}
    assert {
        "RKIdentError",
        "RKIdentWarning",
        "InputValidationError",
        "TableauError",
        "ConvergenceError",
        "IntegrationError",
        "HighIndexError",
        "SingularMatrixError",
        "PoorExcitationWarning",
        "ConvergenceWarning",
        "UnstableModelWarning",
    } <= names
    assert len(names) == len(ALL)  # no class defined twice


@pytest.mark.parametrize("cls", ALL, ids=_ids)
def test_every_class_derives_from_exactly_one_project_base(cls):
    is_error = issubclass(cls, integrators.errors.RKIdentError)
    is_warning = issubclass(cls, integrators.errors.RKIdentWarning)
    assert is_error != is_warning
    assert issubclass(cls, Warning) == is_warning


@pytest.mark.parametrize("cls", ALL, ids=_ids)
def test_every_class_is_public_in_sysid(cls):
    assert getattr(sysid, cls.__name__) is cls and cls.__name__ in sysid.__all__
    assert getattr(sysid.errors, cls.__name__) is cls and cls.__name__ in sysid.errors.__all__


@pytest.mark.parametrize("cls", INTEGRATORS, ids=_ids)
def test_every_integrators_class_is_public_in_integrators(cls):
    assert getattr(integrators, cls.__name__) is cls and cls.__name__ in integrators.__all__


def test_integrators_does_not_know_the_sysid_warnings():
    """Warnings only ``sysid`` issues live in ``sysid.errors``: ``integrators`` never imports
    ``sysid``, so they are not part of ``integrators``' namespace."""
    for cls in SYSID:
        assert not hasattr(integrators, cls.__name__)
        assert not hasattr(integrators.errors, cls.__name__)


@pytest.mark.parametrize(
    "call",
    [
        lambda: sysid.residual_test(torch.randn(50, dtype=torch.float64), max_lag=5.5),
        lambda: sysid.residual_test(torch.randn(50, dtype=torch.float64), alpha=1.5),
        lambda: sysid.residual_test(torch.randn(2, 50, 1), torch.randn(3, 50, 1)),
        lambda: sysid.zoh_discretize(torch.eye(2), torch.ones(2), 0.1),
        lambda: sysid.zoh_discretize(
            torch.eye(2).expand(3, 2, 2), torch.ones(3, 2, 1), torch.ones(4)
        ),
        lambda: sysid.simulate_lti_zoh(
            torch.eye(1), torch.ones(1, 1), torch.zeros(1), torch.ones(5), 0.1
        ),
    ],
    ids=["max_lag float", "alpha > 1", "batch mismatch", "1-D B", "dt batch", "1-D u"],
)
def test_validation_and_discretisation_arguments_are_named_errors(call):
    """A non-integer lag, a level outside (0, 1) (a negative band before), batches that do
    not broadcast and vectors where matrices are expected raise InputValidationError, not a
    torch error from inside."""
    with pytest.raises(sysid.InputValidationError):
        call()


@pytest.mark.parametrize(
    "call",
    [
        lambda: integrators.newton(
            lambda x: x**2 - 2, torch.ones(3, 2, dtype=torch.float64), jacobian=torch.eye(3)
        ),
        lambda: integrators.newton(
            lambda x: x**2 - 2,
            torch.ones(3, 2, dtype=torch.float64),
            jacobian=lambda x: torch.eye(2, dtype=torch.float64).expand(4, 2, 2),
        ),
        lambda: integrators.newton(
            lambda x: x**2 - 2,
            torch.ones(3, 2, dtype=torch.float64),
            method="simplified",
            factorization=torch.linalg.lu_factor(torch.eye(3, dtype=torch.float64)),
        ),
        lambda: integrators.minimize(
            lambda th: (th**2).sum(-1), torch.ones(3, 2, dtype=torch.float64), method="gauss_newton"
        ),
        lambda: integrators.sensitivities(
            lambda t, x, p: -p * x,
            torch.ones(3, 1, dtype=torch.float64),
            torch.linspace(0, 1, 5, dtype=torch.float64),
            p=torch.ones(2, 1, dtype=torch.float64),
        ),
    ],
    ids=["jacobian size", "jacobian batch", "factorization size", "residual w/o m", "p batch"],
)
def test_solver_arguments_of_the_wrong_shape_are_named_errors(call):
    """A Jacobian or factorisation of the wrong size or batch, a residual without its trailing
    axis (it was read as one residual shared by all problems: each problem's loss summed
    the others'), and batches that do not broadcast raise InputValidationError."""
    with pytest.raises(integrators.InputValidationError):
        call()


@pytest.mark.parametrize("value", ["yes", "no", 1, 0])
def test_flags_that_are_not_bools_are_refused(value):
    """A string such as "no" would count as true and a number as a flag: ODELayer's and
    DAELayer's return_solution, newton's and minimize's raise_on_failure, Param's free and
    per_experiment take a bool only."""
    from integrators import ODELayer
    from integrators.dae_layer import DAELayer
    from integrators.errors import InputValidationError
    from integrators.newton import minimize, newton
    from integrators.problems import ImplicitODE
    from sysid.continuous import Param

    x0 = torch.ones(1, dtype=torch.float64)
    problem = ImplicitODE(lambda t, x, xdot: xdot + x)
    calls = [
        (lambda: ODELayer(lambda t, x: -x, return_solution=value), "return_solution"),
        (lambda: DAELayer(problem, return_solution=value), "return_solution"),
        (lambda: newton(lambda x: x - 1, x0, raise_on_failure=value), "raise_on_failure"),
        (lambda: minimize(lambda x: x - 1, x0, raise_on_failure=value), "raise_on_failure"),
        (lambda: Param(1.0, free=value), "free"),
        (lambda: Param(1.0, per_experiment=value), "per_experiment"),
    ]
    for call, name in calls:
        with pytest.raises(InputValidationError, match=rf"{name} must be one of True, False"):
            call()
