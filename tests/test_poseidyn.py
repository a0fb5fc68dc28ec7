"""POSEIDYN LQ-MPC docking (rvdjax.poseidyn; paper 001 Sec. 3.1, Tables 1-3, 6)."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from rvdjax.poseidyn import (
    PUBLISHED,
    PoseidynConfig,
    fly_poseidyn,
    poseidyn_params,
    register,
    validate_poseidyn,
)
from rvdjax.solver import Status

NAMES = ("poseidyn-lqmpc", "poseidyn-lqmpc-retuned")


@pytest.fixture(scope="module")
def scenarios():
    reg: dict = {}
    register(reg)
    return reg


@pytest.fixture(scope="module")
def runs(scenarios):
    """The two tunings differ only in traced data (P scale, F_max): one vmapped program."""
    built = [scenarios[n].build() for n in NAMES]
    sc = scenarios[NAMES[0]]
    assert scenarios[NAMES[1]].config == sc.config
    params = jax.tree.map(lambda *a: np.stack(a), *[b[0] for b in built])
    x0 = np.stack([b[1] for b in built])
    fly = jax.jit(jax.vmap(lambda p, x: sc.fly(p, x, sc.config)))
    return params, fly(params, x0)


def test_register_adds_both_tunings(scenarios):
    assert set(NAMES) <= set(scenarios)
    for name, key in zip(NAMES, ("initial", "retuned"), strict=True):
        sc = scenarios[name]
        assert sc.kind == "poseidyn" and sc.fly is fly_poseidyn
        assert sc.published["effort_l1_N_s"]["LQ-MPC (sim)"] == PUBLISHED[key]["effort_l1_N_s"]
        assert sc.published["time_to_dock_s"]["LQ-MPC (sim)"] == PUBLISHED[key]["time_to_dock_s"]
        assert len(sc.assumptions) >= 5
        params, x0 = sc.build()
        sc.validate(params, x0, sc.config)
    p0, p1 = scenarios[NAMES[0]].build()[0], scenarios[NAMES[1]].build()[0]
    np.testing.assert_allclose(np.asarray(p0.Q_f), 100.0 * np.asarray(p1.Q_f))  # 100 P_bar
    assert float(p0.u_max[0]) == 0.15 and float(p1.u_max[0]) == 0.075


def test_both_tunings_dock_without_violation(runs):
    params, (infos, m) = runs
    assert np.all(np.asarray(m.docked))
    assert np.all(np.asarray(m.koz_violation_m) <= 1e-6)  # truth outside the 0.4 m circle
    assert np.all(np.asarray(m.cone_violation_m) <= 1e-6)  # truth inside the cone in range
    counts = np.asarray(m.status_counts)
    n_active = np.asarray(infos.active).sum(axis=1)
    assert np.all(counts[:, Status.CONVERGED] == n_active)  # accurate mode: all converged
    # the keep-out hyperplane really binds (the chaser is steered around the obstacle) ...
    plane = np.where(np.asarray(infos.active), np.asarray(infos.plane_margin), np.inf)
    assert np.all(np.min(plane, axis=1) < 1e-3)
    # ... and the force limit is reached at the start
    u0 = np.abs(np.asarray(infos.u)[:, 0]).max(axis=1)
    np.testing.assert_allclose(u0, np.asarray(params.u_max)[:, 0], rtol=1e-6)


def test_docked_state_and_effort_definition(runs):
    params, (infos, m) = runs
    for i in range(len(NAMES)):
        n = int(np.sum(infos.active[i]))
        x_last = np.asarray(infos.x[i, n])  # state after the docking step (idle afterwards)
        dt = np.asarray(infos.dt[i])
        assert float(m.time_to_dock_s[i]) == pytest.approx(dt.sum())
        assert (n - 1) * 5.0 < float(m.time_to_dock_s[i]) <= n * 5.0
        # the docking instant lies inside the last step; the step end is still close
        assert np.linalg.norm(x_last[:2] - np.asarray(params.dock[i])) < 0.06
        u = np.asarray(infos.u[i])
        effort = float(np.sum(np.abs(u).sum(axis=1) * dt))  # paper 001 Eq. 14
        assert float(m.effort_l1_N_s[i]) == pytest.approx(effort)


def test_compared_with_paper(runs):
    """Paper 001 Table 6 (LQ-MPC, simulation): 5.3 N s / 102.8 s initial, 5.0 N s / 142.8 s
    re-tuned. rvdjax does NOT reproduce these within 15 % (measured ~3.2 N s / 152 s and
    ~3.0 N s / 154 s, see the module notes): with Q = diag(1e2, 1e2, 1e5, 1e5), R = 1e3 I the
    closed loop has a slow pole exp(-Ts / 31.6 s) whatever P, and F_max binds only at the
    start, so the two tunings fly nearly the same path; the paper's 40 s gap and its effort
    (thruster modulation, un-modelled test-bed effects, undefined docking condition) are not
    reproduced. Only the paper's qualitative trend is asserted: the re-tuned controller costs
    less effort and takes (slightly, here) longer."""
    _, (_, m) = runs
    effort = np.asarray(m.effort_l1_N_s)
    time = np.asarray(m.time_to_dock_s)
    assert effort[1] < effort[0]
    assert time[1] > time[0]
    # sanity bounds, not a match: same order of magnitude as the paper
    assert np.all((effort > 0.4 * 5.0) & (effort < 2.0 * 5.3))
    assert np.all((time > 0.5 * 102.8) & (time < 2.0 * 142.8))


GOOD = dict(x0=(3.5, 3.5, 0.0, 0.0))


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
        (dict(obstacle=(0.75, 0.75), x0=(3.5, 3.5, 0.0, 0.0)), "docking point"),
    ],
)
def test_bad_parameters_raise(change, word):
    with pytest.raises(ValueError, match=word):
        poseidyn_params(**{**GOOD, **change})


def test_bad_config_raises():
    with pytest.raises(ValueError, match="n_steps"):
        PoseidynConfig(n_steps=0)
    with pytest.raises(ValueError, match="x0"):
        validate_poseidyn(None, np.zeros(3), PoseidynConfig())


def test_plot_poseidyn_writes_a_figure(runs, scenarios, tmp_path):
    from rvdjax import plots

    params, (infos, _) = runs
    first = lambda tree: jax.tree.map(lambda a: np.asarray(a)[0], tree)  # noqa: E731
    out = tmp_path / "poseidyn.png"
    plots.plot_poseidyn(out, scenarios[NAMES[0]], first(params), first(infos))
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 20_000
