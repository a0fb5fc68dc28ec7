"""IDVD guidance on the POSEIDYN docking scenario (rvdjax.idvd; paper 001 Sec. 3.2)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("casadi")

from rvdjax.idvd import PUBLISHED_IDVD, run_idvd  # noqa: E402
from rvdjax.poseidyn import poseidyn_params  # noqa: E402


@pytest.fixture(scope="module", params=["initial", "retuned"])
def run(request):
    return run_idvd(request.param)


def test_ipopt_converges(run):
    assert run["solver_success"], run["solver_status"]
    # the plan uses the whole time budget (paper: "usually taking all the allowed time")
    t_max = {"initial": 150.0, "retuned": 100.0}[run["tuning"]]
    assert run["planned_tf_s"] == pytest.approx(t_max, rel=1e-6)


def test_docks_within_poseidyn_tolerance(run):
    p = poseidyn_params()
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
