"""The integration methods by name: one registry and one resolution for every entry point.

``odeint``, ``daeint``, ``solve_implicit_ode`` and ``sensitivities`` accept a method by name
(:data:`METHOD_NAMES`) or as a :class:`~integrators.tableau.ButcherTableau`;
:func:`resolve_method` turns either into a :class:`Method`: its tableau (or the family of
tableaus of a collocation method, by ``stages``), its default kind of run and the options
that apply to each kind. A run's kind follows from the tableau and the ``adaptive`` flag
(:func:`run_kind`):

* ``"explicit-fixed"``: explicit RK at fixed steps (notes eq. 6.6-6.8);
* ``"explicit-adaptive"``: an embedded explicit pair with step-size control (notes §6.5);
* ``"implicit-fixed"``: implicit RK at fixed steps (notes eq. 7.14-7.18);
* ``"implicit-adaptive"``: Radau IIA with an odd number of stages and step-size control;
* ``"auto"``: ``method="auto"``, one of the two adaptive kinds chosen from the stiffness.

An option given explicitly (not left at its default ``None``) for a kind it does not apply to
raises :class:`~integrators.errors.InputValidationError` naming the method and the option
(:meth:`Method.check_options`), instead of being silently ignored.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .collocation import gauss_legendre, radau_iia
from .errors import InputValidationError, TableauError
from .tableau import TABLEAU_NAMES, ButcherTableau, tableau

__all__ = ["KINDS", "METHOD_NAMES", "OPTION_KINDS", "Method", "resolve_method", "run_kind"]

EXPLICIT_FIXED = "explicit-fixed"
EXPLICIT_ADAPTIVE = "explicit-adaptive"
IMPLICIT_FIXED = "implicit-fixed"
IMPLICIT_ADAPTIVE = "implicit-adaptive"
AUTO = "auto"
KINDS = (EXPLICIT_FIXED, EXPLICIT_ADAPTIVE, IMPLICIT_FIXED, IMPLICIT_ADAPTIVE, AUTO)

_ADAPTIVE = frozenset({EXPLICIT_ADAPTIVE, IMPLICIT_ADAPTIVE, AUTO})
_FIXED = frozenset({EXPLICIT_FIXED, IMPLICIT_FIXED})
#: ``odeint``'s options and the kinds of run they apply to (``stages``: the collocation
#: families only, see :attr:`Method.default_stages`).
OPTION_KINDS = {
    "substeps": _FIXED,
    "compile": frozenset({EXPLICIT_FIXED}),
    "checkpoint": frozenset({EXPLICIT_FIXED}),
    "rtol": _ADAPTIVE | {IMPLICIT_FIXED},
    "atol": _ADAPTIVE | {IMPLICIT_FIXED},
    "controller": _ADAPTIVE,
    "dt0": _ADAPTIVE,
    "max_steps": _ADAPTIVE,
}
_OPTION_SCOPE = {
    "substeps": "fixed-step methods (steps per output interval)",
    "compile": "fixed-step explicit methods",
    "checkpoint": "fixed-step explicit methods (adaptive and implicit solvers keep their own "
    "graphs; use sensitivities() or a fixed-step method such as 'rk4')",
    "rtol": "adaptive methods and the Newton solves of implicit ones",
    "atol": "adaptive methods and the Newton solves of implicit ones",
    "controller": "adaptive methods",
    "dt0": "adaptive methods (the first trial step)",
    "max_steps": "adaptive methods",
}
_FIXED_TEXT = "runs at fixed steps (set their number per output interval with substeps)"
_ADAPTIVE_TEXT = "controls its step size (set rtol and atol; pass adaptive=False for fixed steps)"
_KIND_TEXT = {
    EXPLICIT_FIXED: _FIXED_TEXT,
    EXPLICIT_ADAPTIVE: _ADAPTIVE_TEXT,
    IMPLICIT_FIXED: _FIXED_TEXT,
    IMPLICIT_ADAPTIVE: _ADAPTIVE_TEXT,
    AUTO: "picks dopri5 or Radau IIA, both with step-size control (set rtol and atol)",
}


@dataclass(frozen=True)
class Method:
    """One integration method.

    Attributes:
        name: the name it is known by (a tableau's ``name`` for a tableau object).
        kind: the kind of its default run (one of :data:`KINDS`).
        build: ``build(stages) -> ButcherTableau`` (``stages`` is None for a fixed tableau);
            None for ``"auto"``.
        default_stages: the default number of stages of a collocation family; None for a
            method whose number of stages is fixed (``stages=`` is then refused).
    """

    name: str
    kind: str
    build: Callable[[int | None], ButcherTableau] | None
    default_stages: int | None = None

    def tableau(self, stages: int | None = None) -> ButcherTableau:
        """The tableau of this method with ``stages`` stages (collocation families only).

        Raises:
            InputValidationError: ``stages`` given for a method whose stages are fixed.
            TableauError: ``"auto"``, which has no tableau of its own.
        """
        if stages is not None and self.default_stages is None:
            raise InputValidationError(
                f"stages={stages!r} applies to 'gauss_legendre' and 'radau_iia' only, not to "
                f"the method {self.name!r} (its number of stages is fixed)."
            )
        if self.build is None:
            raise TableauError(
                f"method {self.name!r} has no tableau of its own (it chooses a method at run "
                "time); name a method such as 'rk4' or 'radau_iia'."
            )
        return self.build(self.default_stages if stages is None else stages)

    def check_options(self, kind: str, **given) -> None:
        """Refuse every option of ``given`` (name -> value; None means "not given") that does
        not apply to a run of ``kind`` (:data:`OPTION_KINDS`), naming the method and the
        option."""
        for option, value in given.items():
            if value is None or kind in OPTION_KINDS[option]:
                continue
            raise InputValidationError(
                f"{option}={value!r} applies to {_OPTION_SCOPE[option]} only, not to the method "
                f"{self.name!r}, which {_KIND_TEXT[kind]}: remove {option}."
            )


def _default_adaptive(tab: ButcherTableau) -> bool:
    """Whether a run of ``tab`` adapts its step size unless told: explicit pairs with
    ``b_err`` and the named Radau IIA methods with an odd number of stages."""
    if tab.is_explicit:
        return tab.b_err is not None
    return _is_radau(tab) and tab.stages % 2 == 1 and tab.name.startswith("radau_iia")


def run_kind(tab: ButcherTableau, adaptive: bool | None) -> str:
    """The kind of a run of ``tab`` (a method's tableau) with the ``adaptive`` flag
    (None: :func:`_default_adaptive`).

    Raises:
        TableauError: ``adaptive=True`` for an explicit tableau without ``b_err``.
        InputValidationError: ``adaptive=True`` for an implicit tableau other than Radau
            IIA with an odd number of stages; a named Radau IIA tableau with an even number
            of stages and ``adaptive`` not given (the method adapts by default, these cannot).
    """
    radau_odd = _is_radau(tab) and tab.stages % 2 == 1
    if adaptive is None and tab.name.startswith("radau_iia") and not radau_odd:
        raise InputValidationError(
            f"{tab.name!r} has an even number of stages, for which no step-size control is "
            "implemented (its embedded estimate needs a real eigenvalue of A^-1): rtol and "
            "atol would set only the Newton tolerance. Use stages=1, 3 or 5 for an adaptive "
            "run, or pass adaptive=False (and substeps) for fixed steps."
        )
    if adaptive is None:
        adaptive = _default_adaptive(tab)
    if tab.is_explicit:
        if adaptive and tab.b_err is None:
            raise TableauError(
                f"tableau {tab.name!r} has no embedded weights b_err, so it cannot control "
                "its step size; use 'dopri5' or pass adaptive=False."
            )
        return EXPLICIT_ADAPTIVE if adaptive else EXPLICIT_FIXED
    if adaptive and not radau_odd:
        raise InputValidationError(
            f"adaptive step control is implemented for Radau IIA with an odd number of "
            f"stages (its embedded estimate needs a real eigenvalue of A^-1); got "
            f"{tab.name!r}. Use method='radau_iia' with stages=1, 3 or 5, or adaptive=False."
        )
    return IMPLICIT_ADAPTIVE if adaptive else IMPLICIT_FIXED


def _is_radau(tab: ButcherTableau) -> bool:
    """Whether ``tab`` has the coefficients of Radau IIA with its number of stages."""
    ref = radau_iia(tab.stages)
    return np.allclose(tab.A, ref.A, atol=1e-12) and np.allclose(tab.b, ref.b, atol=1e-12)


def _of_tableau(tab: ButcherTableau) -> Method:
    """The method of one fixed tableau, known by the tableau's name."""
    return Method(tab.name, run_kind(tab, _default_adaptive(tab)), lambda _: tab)


_REGISTRY = {
    **{name: _of_tableau(tableau(name)) for name in TABLEAU_NAMES},
    "gauss_legendre": Method("gauss_legendre", IMPLICIT_FIXED, gauss_legendre, 2),
    "radau_iia": Method("radau_iia", IMPLICIT_ADAPTIVE, radau_iia, 3),
    "auto": Method("auto", AUTO, None),
}
#: Every method name the solvers accept.
METHOD_NAMES = tuple(_REGISTRY)


def resolve_method(method) -> Method:
    """The :class:`Method` that ``method`` (a name of :data:`METHOD_NAMES` or a
    :class:`ButcherTableau`) stands for: the one place where methods are resolved.

    Raises:
        TableauError: an unknown name or an object that is neither a name nor a tableau.
    """
    if isinstance(method, ButcherTableau):
        return _of_tableau(method)
    if isinstance(method, str) and method in _REGISTRY:
        return _REGISTRY[method]
    raise TableauError(
        f"unknown method {method!r}; use a ButcherTableau or one of {', '.join(METHOD_NAMES)}."
    )
