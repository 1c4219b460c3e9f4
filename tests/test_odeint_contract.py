"""The documented contract of ``odeint``, as a property over its options and model kinds.

For any options and any kind of model (a plain function, an ``nn.Module`` with a parameter, a
model that calls autograd inside ``f``), ``odeint`` either raises a named exception of the
project's hierarchy, or returns a solution whose successful members match the closed form and
whose failed members carry a status, a message naming them, and NaN after their failure time.

The model is the Bernoulli equation x' = p x^2 - x, whose solution
x(t) = x0 / (p x0 + (1 - p x0) e^t) escapes to infinity at t* = ln(p x0 / (p x0 - 1)) when
p x0 > 1 (compare the notes' eq. 1.44-1.45, the case without the linear term).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from torch import nn

from integrators import InputValidationError, RKIdentError, Status, odeint

DT = torch.float64
N_OUT = 5


def exact(x0: float, p: float, t: np.ndarray) -> np.ndarray:
    return x0 / (p * x0 + (1 - p * x0) * np.exp(t))


def escape_time(x0: float, p: float) -> float:
    return math.log(p * x0 / (p * x0 - 1)) if p * x0 > 1 else math.inf


class Bernoulli(nn.Module):
    def __init__(self, p):
        super().__init__()
        self.p = nn.Parameter(torch.tensor(p, dtype=DT))

    def forward(self, t, x):
        return self.p * x * x - x


class BernoulliFromPotential(Bernoulli):
    """The same field as -dV/dx with V(x) = x^2 / 2 - p x^3 / 3, by autograd inside f."""

    def forward(self, t, x):
        with torch.enable_grad():
            xg = x if x.requires_grad else x.detach().requires_grad_(True)
            v = (0.5 * xg**2 - self.p * xg**3 / 3).sum()
            (dv,) = torch.autograd.grad(v, xg, create_graph=torch.is_grad_enabled())
        return -dv


def make_model(kind: str, p: float):
    if kind == "function":
        return lambda t, x: p * x * x - x
    return Bernoulli(p) if kind == "module" else BernoulliFromPotential(p)


#: (method options, tolerance of a successful member against the closed form)
METHODS = {
    "rk4": (dict(method="rk4", compile=False), 1e-5),
    "euler": (dict(method="euler", compile=False), 5e-2),
    "dopri5": (dict(method="dopri5", rtol=1e-8, atol=1e-10), 1e-5),
    "gauss": (dict(method="gauss_legendre", stages=2, rtol=1e-10), 1e-5),
    "radau fixed": (dict(method="radau_iia", adaptive=False, rtol=1e-10), 1e-5),
    "radau": (dict(method="radau_iia", rtol=1e-8, atol=1e-10), 1e-5),
    "radau host": (dict(method="radau_iia", rtol=1e-8, atol=1e-10, host_loop=True), 1e-5),
    "radau torch": (dict(method="radau_iia", rtol=1e-8, atol=1e-10, host_loop=False), 1e-5),
    "implicit euler": (dict(method="implicit_euler", rtol=1e-10), 5e-2),
}
#: options a user might get wrong, each of which every method must refuse with
#: InputValidationError
BAD_OPTIONS = [
    dict(rtol=1e-17),
    dict(rtol=-1e-6),
    dict(atol=float("nan")),
    dict(substeps=0),
    dict(substeps=2.5),
    dict(adaptive="no"),
    dict(max_steps=0),
]
FIXED = ("rk4", "euler", "gauss", "radau fixed", "implicit euler")


@settings(max_examples=60, deadline=None)
@given(
    method=st.sampled_from(sorted(METHODS)),
    kind=st.sampled_from(["function", "module", "autograd inside f"]),
    batch=st.sampled_from([(), (1,), (3,)]),
    x0s=st.lists(st.sampled_from([-1.0, 0.0, 0.3, 0.9, 1.5, 2.5, 4.0]), min_size=3, max_size=3),
    p=st.sampled_from([0.5, 1.0]),
    t_end=st.sampled_from([0.5, 1.0, 2.0]),
    bad=st.one_of(st.none(), st.sampled_from(range(len(BAD_OPTIONS)))),
    grad=st.booleans(),
)
def test_odeint_raises_a_named_error_or_keeps_its_contract(
    method, kind, batch, x0s, p, t_end, bad, grad
):
    n = int(np.prod(batch)) if batch else 1
    x0s = x0s[:n]
    escapes = [escape_time(x, p) for x in x0s]
    # each member escapes well inside the span, or stays well clear of its escape time
    assume(all(e < 0.8 * t_end or e > 1.5 * t_end for e in escapes))
    options, tol = METHODS[method]
    options = dict(options)
    if method in FIXED:
        options["substeps"] = max(1, math.ceil(t_end / N_OUT / 0.005))
    if bad is not None:
        options.update(BAD_OPTIONS[bad])
    model = make_model(kind, p)
    x0 = torch.tensor(x0s, dtype=DT).reshape(*batch, 1)
    t = torch.linspace(0.0, t_end, N_OUT + 1, dtype=DT)
    try:
        with torch.set_grad_enabled(grad):
            sol = odeint(model, x0, t, **options)
    except InputValidationError:
        assert bad is not None, "valid options were refused"
        return
    except RKIdentError as exc:  # any other named error must not come from valid options
        raise AssertionError(f"unexpected {type(exc).__name__}: {exc}") from exc
    assert bad is None, f"{BAD_OPTIONS[bad]} was accepted by {method}"
    status = sol.status.reshape(-1)
    x = sol.x.detach().reshape(n, N_OUT + 1).numpy()
    for k, (x0, escape) in enumerate(zip(x0s, escapes, strict=True)):
        if escape < 0.8 * t_end:
            assert status[k] != Status.SUCCESS, f"member {k} escapes at {escape:.3f}"
            named = [m for m in sol.messages if n == 1 or f"sample {k}" in m or f"({k},)" in m]
            assert named, sol.messages
            after = t.numpy() > escape + 0.05
            assert np.isnan(x[k, after]).all(), x[k]
            before = t.numpy() < 0.5 * escape
            ref = exact(x0, p, t.numpy()[before])
            err = np.abs(x[k, before] - ref) / (1 + np.abs(ref))
            assert (err <= tol).all(), (k, err)
        else:
            assert status[k] == Status.SUCCESS, sol.messages
            ref = exact(x0, p, t.numpy())
            err = np.abs(x[k] - ref) / (1 + np.abs(ref))
            assert (err <= tol).all(), (k, err)
    if grad and kind != "function" and all(e > t_end for e in escapes):
        (g,) = torch.autograd.grad(sol.x[..., -1, :].sum(), model.p)
        x0a, e = np.array(x0s), math.exp(t_end)
        dxdp = -(x0a * x0a * (1 - e)) / (p * x0a + (1 - p * x0a) * e) ** 2  # d/dp of exact()
        assert abs(float(g) - dxdp.sum()) <= 10 * tol * (1 + abs(dxdp.sum()))
