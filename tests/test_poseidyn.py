"""The POSEIDYN family (paper 001 Sec. 3.1, Tables 1-3, 6) through the closed-loop kernel."""

from __future__ import annotations

import numpy as np
import pytest
from flights import flight

from rvdjax.families.poseidyn import plane_angle
from rvdjax.scenarios import SCENARIOS
from rvdjax.scenarios.paper001 import PUBLISHED
from rvdjax.solver import Status

NAMES = ("poseidyn-lqmpc", "poseidyn-lqmpc-retuned")


@pytest.fixture(scope="module")
def runs():
    """The two tunings differ only in traced data (P scale, F_max): one vmapped program."""
    return flight(NAMES)


def test_scenarios_carry_both_tunings():
    for name, key in zip(NAMES, ("initial", "retuned"), strict=True):
        sc = SCENARIOS[name]
        assert sc.family == "poseidyn"
        assert sc.published["effort_l1_N_s"]["LQ-MPC (sim)"] == PUBLISHED[key]["effort_l1_N_s"]
        assert sc.published["time_to_dock_s"]["LQ-MPC (sim)"] == PUBLISHED[key]["time_to_dock_s"]
        assert len(sc.assumptions) >= 5
    p0, p1 = SCENARIOS[NAMES[0]].build()[0], SCENARIOS[NAMES[1]].build()[0]
    np.testing.assert_allclose(np.asarray(p0.Q_f), 100.0 * np.asarray(p1.Q_f))  # 100 P_bar
    assert float(p0.u_max[0]) == 0.15 and float(p1.u_max[0]) == 0.075


def test_both_tunings_dock_without_violation(runs):
    _, params, infos, m = runs
    assert np.all(m.docked)
    assert np.all(m.margins_m["keep_out"] >= -1e-6)  # truth outside the 0.4 m circle
    assert np.all(m.margins_m["entry_cone"] >= -1e-6)  # truth inside the cone in range
    assert np.all(m.max_violation_m <= 1e-6)
    n_active = infos.active.sum(axis=1)
    assert np.all(m.status_counts[:, Status.CONVERGED] == n_active)  # accurate: all converged
    # the keep-out hyperplane really binds (the chaser is steered around the obstacle) ...
    plane = np.where(infos.active[..., None], infos.margins["keep_out_plane"], np.inf)
    assert np.all(np.min(plane, axis=(1, 2)) < 1e-3)
    # ... and the force limit is reached at the start
    u0 = np.abs(infos.u[:, 0]).max(axis=1)
    np.testing.assert_allclose(u0, params.u_max[:, 0], rtol=1e-6)


def test_docked_state_and_effort_definition(runs):
    _, params, infos, m = runs
    for i in range(len(NAMES)):
        n = int(np.sum(infos.active[i]))
        x_last = infos.x[i, n]  # state after the docking step (idle afterwards)
        dt = infos.dt[i]
        assert float(m.time_to_dock_s[i]) == pytest.approx(dt.sum())
        assert (n - 1) * 5.0 < float(m.time_to_dock_s[i]) <= n * 5.0  # docked inside a step
        assert np.linalg.norm(x_last[:2] - params.dock[i]) < 0.06
        effort = float(np.sum(np.abs(infos.u[i]).sum(axis=1) * dt))  # paper 001 Eq. 14
        assert float(m.effort_l1_N_s[i]) == pytest.approx(effort)
    # the plane angle turns at the fixed rate, then holds
    t = infos.t[0, : int(infos.active[0].sum())]
    phi = np.asarray(plane_angle(params_at(params, 0), t))
    assert np.all(np.diff(phi) >= -1e-12) and phi[-1] <= float(params.phi_final[0]) + 1e-12


def params_at(params, i):
    import jax

    return jax.tree.map(lambda a: a[i], params)


def test_compared_with_paper(runs):
    """Paper 001 Table 6 (LQ-MPC, simulation): 5.3 N s / 102.8 s initial, 5.0 N s / 142.8 s
    re-tuned. rvdjax does NOT reproduce these within 15 % (measured ~3.2 N s / 152 s and
    ~3.0 N s / 154 s; docs/reproduction.md): with Q = diag(1e2, 1e2, 1e5, 1e5), R = 1e3 I the
    closed loop has a slow pole exp(-Ts / 31.6 s) whatever P, and F_max binds only at the
    start, so the two tunings fly nearly the same path. Only the paper's qualitative trend is
    asserted: the re-tuned controller costs less effort and takes longer."""
    _, _, _, m = runs
    effort, time = m.effort_l1_N_s, m.time_to_dock_s
    assert effort[1] < effort[0]
    assert time[1] > time[0]
    # sanity bounds, not a match: same order of magnitude as the paper
    assert np.all((effort > 0.4 * 5.0) & (effort < 2.0 * 5.3))
    assert np.all((time > 0.5 * 102.8) & (time < 2.0 * 142.8))


@pytest.mark.parametrize(
    "change, word",
    [
        (dict(mass=0.0), "mass"),
        (dict(mass=-10.0), "mass"),
        (dict(ts=0.0), "ts"),
        (dict(half_angle_deg=0.0), "half_angle"),
        (dict(half_angle_deg=90.0), "half_angle"),
        (dict(u_max=-0.15), "u_max"),
        (dict(r_obs=0.0), "r_obs"),
        (dict(cone_range=-0.5), "cone_range"),
        (dict(plane_rate_deg_s=0.0), "plane_rate"),
        (dict(plane_direction=0), "plane_direction"),
        (dict(terminal_scale=0.0), "terminal_scale"),
        (dict(dock_tol=0.0), "dock_tol"),
        (dict(R=(1e3, -1.0)), "R must be positive definite"),
        (dict(Q=(1.0, 1.0, -1.0, 1.0)), "Q must be positive semidefinite"),
        (dict(x0=(2.6, 2.6, 0.0, 0.0)), "inside the keep-out zone"),
        (dict(x0=(3.5, 3.5, 0.0)), "x0"),
        (dict(x0=(3.5, np.nan, 0.0, 0.0)), "x0"),
        (dict(obstacle=(0.75, 0.75)), "docking point"),
    ],
)
def test_bad_parameters_raise(change, word):
    with pytest.raises(ValueError, match=word):
        SCENARIOS[NAMES[0]].build(**change)


def test_bad_config_raises():
    with pytest.raises(ValueError, match="substeps"):
        SCENARIOS[NAMES[0]].loop(substeps=0)
    with pytest.raises(ValueError, match="n_steps"):
        SCENARIOS[NAMES[0]].loop(n_steps=0)
