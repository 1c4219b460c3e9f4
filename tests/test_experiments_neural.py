"""Run the neural-ODE training scripts in --quick mode and check the numbers they report
(issue 14 acceptance: Van der Pol free-run fit, energy drift of the Lagrangian network, the
hybrid model's unbiased physical parameters next to a learned friction)."""

from experiments import neural_hybrid_friction, neural_lagrangian, neural_vanderpol
from experiments._common import figure_defects


def test_neural_vanderpol_free_run_fit(tmp_path, saved_figures):
    (row,) = neural_vanderpol.main(["--quick", "--out", str(tmp_path)])
    for name, fig in saved_figures.items():
        assert figure_defects(fig) == [], name
    # acceptance: free run from a held-out initial condition (10 s, a limit-cycle period
    # and a half), both states >= 95 % fit
    assert row["val_fit_min_pct"] >= 95.0
    assert row["val_r2_min"] > 0.99
    assert row["final_train_loss"] < 2e-3
    assert (tmp_path / "summary.csv").exists() and (tmp_path / "neural_vanderpol.png").exists()


def test_neural_lagrangian_energy_drift_at_equal_training_loss(tmp_path, saved_figures):
    rows, ratio = neural_lagrangian.main(["--quick", "--out", str(tmp_path)])
    for name, fig in saved_figures.items():
        assert figure_defects(fig) == [], name
    mlp, lnn, grey = rows
    # equal training loss: the same window loss, within a factor 2 of each other
    assert 0.5 <= ratio["train_loss_ratio_mlp_over_lnn"] <= 2.0
    assert lnn["reached_target"]
    # acceptance: the Lagrangian network's energy drift over 60 s (about 30 periods) is at
    # least 10x smaller than the plain MLP's
    assert ratio["energy_drift_ratio_mlp_over_lnn"] >= 10.0
    assert lnn["energy_drift"] < 0.1
    # the grey-box pendulum recovers L = 1 m and rolls out near the 1e-4 floor
    assert abs(grey["L_hat"] - 1.0) < 1e-3
    assert grey["rollout_rms_error"] < 50 * grey["floor_rms_error"]
    assert lnn["rollout_rms_error"] < mlp["rollout_rms_error"]


def test_neural_hybrid_friction_unbiased_parameters_and_learned_friction(tmp_path, saved_figures):
    (grey, hybrid), curves = neural_hybrid_friction.main(["--quick", "--out", str(tmp_path)])
    for name, fig in saved_figures.items():
        assert figure_defects(fig) == [], name
    # acceptance: the hybrid's physical parameters lie within 3 standard errors of the truth
    # (measured: m -2.0 SE, k -1.5 SE)
    assert abs(hybrid["m_error_in_se"]) <= 3.0
    assert abs(hybrid["k_error_in_se"]) <= 3.0
    # the grey-box model without friction is biased: its viscous c absorbs the friction
    # (measured: c +44 SE, m +4.4 SE)
    assert grey["c_error_in_se"] > 10.0
    assert grey["max_abs_error_in_se"] > 3.0
    # the hybrid's validation free run is clearly better (measured: 96.8 / 95.6 % vs 72 / 73 %)
    assert hybrid["val_fit_position_pct"] > 93.0 and hybrid["val_fit_velocity_pct"] > 92.0
    assert grey["val_fit_position_pct"] < hybrid["val_fit_position_pct"] - 15.0
    # the learned velocity-dependent force -m r(v) follows c v + F(v) on the training
    # velocity range (measured relative RMS 0.038)
    v, learned = curves["v"], curves["learned_force"]
    true = neural_hybrid_friction.TRUE["c"] * v + neural_hybrid_friction.friction(v)
    assert float((learned - true).norm() / true.norm()) < 0.08
    assert hybrid["force_rel_rms"] < 0.08
    assert (tmp_path / "neural_hybrid_friction.csv").exists()
    assert (tmp_path / "neural_hybrid_friction.png").exists()
