"""The mechanics benchmark runs in --quick mode and its two right-hand sides agree."""

from experiments.bench_mechanics import main


def test_bench_mechanics_quick_builder_equals_hand_written_form(tmp_path):
    rows = main(["--quick", "--out", str(tmp_path)])
    assert {r["case"].split()[0] for r in rows} == {"chain", "two-pendulum"}
    for row in rows:
        # the autograd builder and the hand-written closed form compute the same accelerations
        assert float(row["max_abs_diff"]) < 1e-10
        assert row["builder_ms"] > 0 and row["closed_form_ms"] > 0
        assert abs(row["ratio"] - row["builder_ms"] / row["closed_form_ms"]) < 0.05 * row["ratio"]
    assert (tmp_path / "bench_mechanics.md").read_text().count("chain") == 2
    assert (tmp_path / "bench_mechanics.csv").exists()
