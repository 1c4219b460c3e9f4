"""experiments/newton_convergence.py: the rates it reports match Theorems 3, 4 and 6."""

import csv
import math

from experiments.newton_convergence import main


def test_newton_convergence_quick(tmp_path):
    main(["--quick", "--out", str(tmp_path)])
    assert (tmp_path / "newton_convergence.png").stat().st_size > 10_000
    assert (tmp_path / "newton_convergence.md").read_text().startswith("| problem")
    with open(tmp_path / "newton_convergence.csv") as handle:
        rows = {(r["problem"], r["variant"]): r for r in csv.DictReader(handle)}
    for problem in ("scalar", "vector"):
        exact = rows[(problem, "exact Jacobian")]
        assert exact["converged"] == "True" and int(exact["iterations"]) <= 7
        assert float(exact["observed_order"]) > 1.8  # quadratic (Theorem 3)
        for variant in ("M frozen at x0", "M = 1.5 J"):
            approx = rows[(problem, variant)]
            assert approx["converged"] == "True"
            assert abs(float(approx["observed_order"]) - 1.0) < 0.1  # linear (Theorem 6)
            # the observed linear rate is the predicted kappa = rho(I - M^{-1} J(x*))
            assert math.isclose(
                float(approx["linear_rate"]), float(approx["predicted_ratio"]), rel_tol=2e-3
            )
            assert int(approx["iterations"]) > 3 * int(exact["iterations"])
    assert rows[("arctan", "full steps")]["converged"] == "False"
    assert float(rows[("arctan", "full steps")]["final_error"]) > 1e3  # diverged
    damped = rows[("arctan", "damped (Armijo)")]
    assert damped["converged"] == "True" and float(damped["final_error"]) < 1e-12
