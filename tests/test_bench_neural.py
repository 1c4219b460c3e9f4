"""experiments/bench_neural.py --quick: ours and torchdiffeq's odeint train the same network
on the same minibatches through the same 3/8-rule grid, so their losses agree to rounding;
the adjoint saves (almost) nothing for backward in its forward pass."""

import pytest

from experiments.bench_neural import main, peers, saved_bytes, vdp_data


@pytest.fixture(scope="module")
def rows(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench_neural")
    return {r["peer"]: r for r in main(["--quick", "--out", str(out)])}


def test_table_complete(rows):
    assert set(rows) == set(peers(quick=True)) and "ours, compiled" not in rows
    for row in rows.values():
        assert row["seconds_per_epoch"] > 0 and row["saved_mb_long_gradient"] > 0
    assert rows["ours"]["time_vs_ours"] == 1.0


def test_losses_agree(rows):
    ours = rows["ours"]["loss_after_epochs"]
    assert rows["torchdiffeq odeint"]["loss_after_epochs"] == pytest.approx(ours, rel=1e-9)
    # the discretised adjoint's gradient differs slightly from backpropagation's
    assert rows["torchdiffeq odeint_adjoint"]["loss_after_epochs"] == pytest.approx(ours, rel=1e-3)


def test_adjoint_saves_little(rows):
    ours = rows["ours"]["saved_mb_long_gradient"]
    assert rows["torchdiffeq odeint"]["saved_mb_long_gradient"] == pytest.approx(ours, rel=0.05)
    assert rows["torchdiffeq odeint_adjoint"]["saved_mb_long_gradient"] < 0.2 * ours


def test_saved_bytes_count_the_weights_once():
    """Every stage of every step saves a view of each layer's weight; the memory a step adds
    is its activations (hundreds of floats), far below one 64 x 64 weight (32 KiB), which the
    former count added 8 times per step (281 MB for 8 MB at 2000 steps)."""
    data = vdp_data(201)
    small, large = (saved_bytes("ours", data, 64, n) for n in (100, 200))
    per_step = (large - small) / 100
    assert 0 < per_step < 64 * 64 * 8
