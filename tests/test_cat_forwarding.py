"""The cat-forwarding graph pass (integrators/_fast/cat_forwarding.py) and its component-wise test.

The pass must only remove data movement: the rewritten graph computes bit-for-bit the values
of the original, for every way a model may take its state apart (``unbind``, ``x[..., i]``,
slices, negative indices) and put its derivative together (``stack``, ``cat`` of slices or of
wider pieces).
"""

import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch._inductor.decomposition import select_decomp_table
from torch.fx.experimental.proxy_tensor import make_fx

from integrators._fast.cat_forwarding import forward_cat_reads, reads_only_components
from integrators._fast.passes import scale_alpha_operands

DT = torch.float64


def _traced(fn, *args):
    """``fn`` traced at the ATen level with inductor's decompositions (what the pass sees)."""
    with torch.no_grad():
        return make_fx(fn, decomposition_table=select_decomp_table())(*args)


def _cats(gm) -> int:
    targets = (torch.ops.aten.cat.default, torch.ops.aten.stack.default)
    return sum(node.op == "call_function" and node.target in targets for node in gm.graph.nodes)


def _rewritten_equals_original(fn, *args):
    """Rewrite ``fn``'s graph; returns (rewrites, cats left) after checking the values."""
    gm = _traced(fn, *args)
    expected = gm(*args)
    n = forward_cat_reads(gm.graph)
    gm.recompile()
    got = gm(*args)
    for a, b in zip(got, expected, strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape
        assert torch.equal(a, b)
    return n, _cats(gm)


def van_der_pol_stacked(t, x):
    x1, x2 = x.unbind(-1)
    return torch.stack([(1 - x2 * x2) * x1 - x2, x1], dim=-1)


def van_der_pol_sliced(t, x):
    x1, x2 = x[..., 0:1], x[..., -1:]
    return torch.cat([(1 - x2**2) * x1 - x2, x1], dim=-1)


def _rk2_step(f):
    """A midpoint step on components, the way the component-major chunk forms stages."""

    def step(*components):
        K1 = f(0.0, torch.stack(components, dim=-1))
        mid = [c + 0.05 * K1[..., i] for i, c in enumerate(components)]
        K2 = f(0.05, torch.stack(mid, dim=-1))
        return tuple(c + 0.1 * K2[..., i] for i, c in enumerate(components))

    return step


def test_stacked_and_sliced_models_lose_every_concatenation():
    """A two-stage step of Van der Pol written with unbind/stack or with slices/cat: every
    stack and cat is forwarded away and the values are unchanged."""
    x = torch.randn(5, 2, dtype=DT, generator=torch.Generator().manual_seed(0))
    for f in (van_der_pol_stacked, van_der_pol_sliced):
        step = _rk2_step(f)
        assert _cats(_traced(step, *x.unbind(-1))) >= 3
        n, left = _rewritten_equals_original(step, *x.unbind(-1))
        assert n >= 4 and left == 0
        assert reads_only_components(lambda z, f=f: f(0.0, z), x)


def test_reads_of_wide_pieces_and_negative_indices():
    """cat of a 2-wide piece and a 1-wide piece, read by negative index, by a slice inside
    the wide piece and by a slice spanning both (which must stay a cat)."""

    def fn(a, b, c):
        wide = torch.stack([a * 2, b + 1], dim=-1)  # (n, 2)
        y = torch.cat([wide, c.unsqueeze(-1)], dim=-1)  # (n, 3)
        return y[..., -1], y[..., 1], y[..., 0:2].sum(-1), y[..., 1:3] * 3, y[..., -3:-2]

    args = [torch.randn(4, dtype=DT, generator=torch.Generator().manual_seed(s)) for s in (1, 2, 3)]
    n, left = _rewritten_equals_original(fn, *args)
    assert n >= 3 and left == 2  # the spanning slice keeps the outer cat (and the wide stack)


def test_type_promoting_cat_is_not_forwarded():
    """A cat that promotes float32 to float64 is read as float64: forwarding its float32 piece
    would change the dtype, so the pass leaves it."""

    def fn(a, b):
        y = torch.cat([a.unsqueeze(-1), b.unsqueeze(-1)], dim=-1)
        return y[..., 0], y[..., 1]

    a = torch.randn(3, dtype=torch.float32)
    b = torch.randn(3, dtype=DT)
    n, left = _rewritten_equals_original(fn, a, b)
    assert left == 1 and n == 0


def test_models_mixing_components_are_not_component_wise():
    A = torch.tensor([[0.0, 1.0], [-2.0, -0.3]], dtype=DT)
    x = torch.randn(4, 2, dtype=DT)
    assert not reads_only_components(lambda z: z @ A.T, x)
    assert not reads_only_components(lambda z: z - z.sum(-1, keepdim=True), x)
    assert not reads_only_components(lambda z: torch.flip(z, (-1,)), x)

    def untraceable(z):
        if float(z[0, 0]) > 0:  # data-dependent Python control flow on a traced value
            return z
        return -z

    assert not reads_only_components(untraceable, x)


_UNARY = {
    "sin": torch.sin,
    "square": lambda v: v * v,
    "neg": torch.neg,
    "scale": lambda v: 0.5 * v + 1,
}


@st.composite
def component_models(draw):
    """A random component-wise model: each output component is a unary function of one input
    component times another one, and the result is assembled as a stack, a cat of (…, 1)
    slices, or a cat mixing a 2-wide stacked piece with slices."""
    nx = draw(st.integers(1, 4))
    terms = [
        (
            draw(st.sampled_from(sorted(_UNARY))),
            draw(st.integers(-nx, nx - 1)),
            draw(st.integers(0, nx - 1)),
        )
        for _ in range(nx)
    ]
    style = draw(st.sampled_from(["stack", "cat_slices", "cat_wide"]))
    take = draw(st.sampled_from(["unbind", "index", "slice"]))

    def f(t, x):
        if take == "unbind":
            comps = x.unbind(-1)
        elif take == "index":
            comps = [x[..., i] for i in range(nx)]
        else:
            comps = [x[..., i : i + 1].squeeze(-1) for i in range(nx)]
        outs = [_UNARY[u](comps[i]) * comps[j] for u, i, j in terms]
        if style == "stack" or nx == 1:
            return torch.stack(outs, dim=-1)
        if style == "cat_slices":
            return torch.cat([o.unsqueeze(-1) for o in outs], dim=-1)
        return torch.cat(
            [torch.stack(outs[:2], dim=-1)] + [o.unsqueeze(-1) for o in outs[2:]], dim=-1
        )

    return nx, f


@settings(max_examples=15, deadline=None)
@given(model=component_models(), batch=st.integers(1, 6), seed=st.integers(0, 1000))
def test_random_component_wise_models(model, batch, seed):
    """Any component-wise model: its two-stage step loses every concatenation, gives the same
    bits, and the model is recognised as component-wise."""
    nx, f = model
    x = torch.randn(batch, nx, dtype=DT, generator=torch.Generator().manual_seed(seed))
    _, left = _rewritten_equals_original(_rk2_step(f), *x.unbind(-1))
    assert left == 0
    assert reads_only_components(lambda z: f(0.0, z), x)


def test_alpha_of_add_and_sub_becomes_a_product():
    """``add(a, b, alpha=c)`` and ``sub(a, b, alpha=c)`` (inductor drops c when ``b`` is a
    matrix product) are rewritten into ``a + b * c`` and ``a - b * c`` with the same values;
    ``alpha = 1`` is left alone."""
    W = torch.tensor([[0.0, 2.0], [-2.0, 0.5]], dtype=DT)
    x = torch.tensor([[1.0, 0.5], [0.25, -1.0]], dtype=DT)

    def model(x):
        y = torch.add(-x, x @ W.T, alpha=0.5)
        return torch.sub(y, torch.nn.functional.linear(x, W), alpha=-3.0) + torch.add(x, y)

    gm = _traced(model, x)
    expected = gm(x)
    assert scale_alpha_operands(gm.graph) == 2
    gm.recompile()
    assert not any("alpha" in node.kwargs for node in gm.graph.nodes)
    torch.testing.assert_close(gm(x), expected, rtol=1e-15, atol=1e-15)
    torch.testing.assert_close(gm(x), model(x), rtol=1e-15, atol=1e-15)
