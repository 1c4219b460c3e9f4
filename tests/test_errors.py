"""The exception and warning hierarchy shared by ``integrators`` and ``sysid``."""

import inspect

import pytest

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
