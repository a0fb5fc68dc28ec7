"""IDVD guidance on the POSEIDYN docking scenario (rvdjax.idvd; paper 001 Sec. 3.2)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("casadi")

from rvdjax.idvd import PUBLISHED_IDVD, run_idvd  # noqa: E402
from rvdjax.scenarios import SCENARIOS  # noqa: E402


@pytest.fixture(scope="module", params=["initial", "retuned"])
def run(request):
    return run_idvd(request.param)


def test_ipopt_converges(run):
    assert run["solver_success"], run["solver_status"]
    # the plan uses the whole time budget (paper: "usually taking all the allowed time")
    t_max = {"initial": 150.0, "retuned": 100.0}[run["tuning"]]
    assert run["planned_tf_s"] == pytest.approx(t_max, rel=1e-6)


def test_docks_within_poseidyn_tolerance(run):
    p, _ = SCENARIOS["poseidyn-lqmpc"].build()
    assert run["docked"]
    assert run["final_pos_err_m"] < float(p.dock_tol)
    assert run["final_speed_m_s"] < float(p.dock_speed_tol)


def test_no_constraint_violation_and_thrust_limit(run):
    assert run["koz_violation_m"] <= 1e-3
    assert run["cone_violation_m"] <= 1e-3
    assert run["max_abs_force_N"] <= run["u_max_N"] * (1 + 1e-6)


def test_keep_out_fine_grid_on_plan(run):
    plan = run["plan"]
    r = plan.position(np.linspace(0.0, plan.tf, 20001))
    d = np.linalg.norm(r - np.array([2.5, 2.5]), axis=1)
    assert np.min(d) >= 0.4 - 1e-3


def test_effort_vs_paper(run):
    """Paper 001 Table 6 (IDVD sim): 2.4 N s / 148.0 s (initial), 6.0 N s / 90.2 s
    (re-tuned). The one-shot plan on an ideal truth is cheaper than the paper's 5 Hz
    re-planned flight with delta-sigma thrusters, and docks (0.05 m / 0.05 m/s) well before
    t_max because the polynomial approach is slow at the end; assert only that IDVD stays
    below the paper's IDVD effort and below LQ-MPC's 5.3 N s (initial tuning)."""
    pub = PUBLISHED_IDVD[run["tuning"]]
    assert run["effort_l1_N_s"] < pub["effort_l1_N_s"]
    assert run["effort_l1_N_s"] < 5.3
    assert run["time_to_dock_s"] <= run["planned_tf_s"]


@pytest.mark.slow  # 17 s; `pytest -m slow`
def test_replanning_at_5_hz_as_the_paper():
    """Paper 001 Sec. 5: IDVD re-solved at 5 Hz with at most 15 IPOPT iterations, warm started
    ("convergence was usually achieved under ten iterations"), uses the whole time budget.
    Re-tuned case: docks without violation, re-plans converge in < 10 iterations on average
    and nearly all are flown, and the time to dock is within 15 % of Table 6's 90.2 s."""
    res = run_idvd("retuned", replan_period_s=0.2, replan_max_iter=15)
    assert res["docked"] and res["max_violation_m"] <= 1e-3
    assert res["max_abs_force_N"] <= res["u_max_N"] * (1 + 1e-6)
    assert res["n_solves"] > 300 and res["n_failed_replans"] <= 0.05 * res["n_solves"]
    assert res["mean_replan_iterations"] < 10
    pub = PUBLISHED_IDVD["retuned"]
    assert res["time_to_dock_s"] == pytest.approx(pub["time_to_dock_s"], rel=0.15)
    assert res["time_to_dock_s"] <= 100.0  # the re-tuned budget t_max
    assert res["effort_l1_N_s"] < pub["effort_l1_N_s"]
