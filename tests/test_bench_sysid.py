"""Run the estimator benchmark in --quick mode and check that the methods agree (not time)."""

from experiments import bench_sysid


def test_bench_sysid_quick_agreement(tmp_path):
    rows = bench_sysid.main(["--quick", "--out", str(tmp_path)])
    fir = [r for r in rows if r["task"].startswith("300 FIR")]
    assert len(fir) == 3
    assert all(r["max_param_diff_vs_numpy"] < 1e-10 for r in fir)
    # sigma^2 (fir_lls: from r'r = y'y - 2 theta'c + theta'U'U theta) agrees with numpy's
    # residual sum of squares
    assert all(r["max_sigma2_rel_diff_vs_numpy"] < 1e-10 for r in fir)
    oe = {r["method"]: r for r in rows if r["task"].startswith("OE(4,4) fit")}
    ours, scipy_fit = oe["sysid.fit gauss_newton"], oe["scipy least_squares (trf, 2-point)"]
    # both reach the same least-squares optimum (cost and parameters)
    assert abs(ours["final_cost"] - scipy_fit["final_cost"]) < 1e-6 * scipy_fit["final_cost"]
    assert abs(ours["param_error_vs_truth"] - scipy_fit["param_error_vs_truth"]) < 2e-3
    assert ours["param_error_vs_truth"] < 0.05
    # started where scipy starts (our automatic initial estimate), the same optimum
    same = oe["sysid.fit gauss_newton, same start as scipy"]
    assert abs(same["final_cost"] - ours["final_cost"]) < 1e-9 * ours["final_cost"]
    grads = [r for r in rows if "gradient" in r["task"]]
    assert all(r["grad_rel_diff"] < 1e-10 for r in grads)
    # both of our paths (CPU dispatch to scipy, pure-torch block method) are reported
    assert sum(r["method"].startswith("ours") for r in grads) == 2
    # the compacted batched fits equal the uncompacted batch and the split batches exactly
    pem = [r for r in rows if r["task"].startswith("16 ")]
    assert {r["task"] for r in pem} == {"16 BJ(2,1,1,2) fits, N=300", "16 OE(2,2) fits, N=300"}
    assert len(pem) == 6
    assert all(r["max_param_diff_vs_uncompacted"] < 1e-12 and r["same_iterations"] for r in pem)
    assert (tmp_path / "bench_sysid.md").exists()
