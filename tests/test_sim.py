"""Closed loop (rvdjax.sim) on the fastmpc-3d scenario of paper 000 Sec. IV.A."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rvdjax.cli import main
from rvdjax.scenarios import SCENARIOS, get_scenario
from rvdjax.sim import run_closed_loop, run_reference_loop, validate_loop
from rvdjax.solver import SolverSettings, Status

SC = get_scenario("fastmpc-3d")
PARAMS, X0 = SC.build()
# One compiled program per solver mode, shared by every test (and by both scenarios: the
# obstacle-free case only changes the traced obstacle mask).
CONFIGS = {
    "accurate": dataclasses.replace(SC.config, settings=SolverSettings()),
    "paper": dataclasses.replace(SC.config, settings=SolverSettings.paper()),
}
FLY = {
    mode: jax.jit(lambda p, x, c=config: run_closed_loop(p, x, c))
    for mode, config in CONFIGS.items()
}
PAPER_IMPULSE_KN_S = SC.published["effort_l1_N_s"]["Fast MPC"] / 1e3


@pytest.fixture(scope="module")
def accurate_run():
    return FLY["accurate"](PARAMS, X0)


def test_fastmpc3d_docks_without_violation(accurate_run):
    infos, m = accurate_run
    assert bool(m.docked)
    final = np.asarray(infos.x)[int(np.sum(infos.active)) - 1]
    assert np.linalg.norm(final[:3]) > float(PARAMS.stop_radius)  # last active step: outside
    assert float(m.max_violation_m) <= 1e-6
    counts = np.asarray(m.status_counts)
    assert counts[Status.CONVERGED] == int(np.sum(infos.active)) and counts[1:].sum() == 0
    # no NaN anywhere in the record
    for field in infos:
        assert not np.any(np.isnan(np.asarray(field, dtype=float)))


def test_fastmpc3d_total_impulse_matches_paper(accurate_run):
    """Paper 000: Fast MPC 33.98 kN s (ISNM 33.80, IPOPT NMPC 32.93, fmincon 34.33).

    Measured: 33.46 kN s (L1 sum), -1.5 %. The issue asks for 15 %.
    """
    _, m = accurate_run
    ours = float(m.effort_l1_N_s) / 1e3
    assert abs(ours - PAPER_IMPULSE_KN_S) / PAPER_IMPULSE_KN_S < 0.15
    # L2 <= L1 <= sqrt(3) L2 (three axes)
    l2 = float(m.total_impulse_N_s) / 1e3
    assert l2 <= ours <= np.sqrt(3) * l2 + 1e-9


def test_same_trajectory_as_clarabel_in_the_loop(accurate_run):
    """rvdjax (accurate) and Clarabel solve the same QPs each step: same trajectory."""
    infos, m = accurate_run
    ref_infos, ref_m, _ = run_reference_loop(PARAMS, X0, SC.config)
    n = int(np.sum(ref_infos.active))
    assert n == int(np.sum(infos.active))
    dx = np.max(np.abs(np.asarray(infos.x)[:n, :3] - ref_infos.x[:n, :3]))
    du = np.max(np.abs(np.asarray(infos.u)[:n] - ref_infos.u[:n]))
    assert dx <= 1e-3  # metres, over a 1 km approach (measured 5e-5)
    assert du <= 1e-3 * float(PARAMS.u_max[0])  # measured 2e-4 N of 20 N
    assert abs(float(m.effort_l1_N_s) - float(ref_m.effort_l1_N_s)) <= 1e-6 * float(
        ref_m.effort_l1_N_s
    )


def test_paper_mode_closed_loop():
    """Paper mode docks too, with only converged / max-iteration statuses."""
    infos, m = FLY["paper"](PARAMS, X0)
    assert bool(m.docked)
    assert float(m.max_violation_m) <= 1e-6
    counts = np.asarray(m.status_counts)
    assert counts[Status.INFEASIBLE] == 0 and counts[Status.NONFINITE] == 0
    ours = float(m.effort_l1_N_s) / 1e3
    assert abs(ours - PAPER_IMPULSE_KN_S) / PAPER_IMPULSE_KN_S < 0.15


def test_obstacle_free_variant_and_batch():
    """vmap over initial conditions (one program), obstacle-free variant via the mask."""
    free, x0 = SCENARIOS["fastmpc-3d-free"].build()
    assert float(free.obstacle_mask.sum()) == 0.0
    x0s = jnp.stack([X0, X0 + jnp.array([10.0, -20.0, 5.0, 0.0, 0.0, 0.0])])
    batched = jax.jit(jax.vmap(FLY["accurate"], in_axes=(None, 0)))
    infos, m = batched(free, x0s)
    assert np.all(np.asarray(m.docked))
    single_infos, single_m = FLY["accurate"](free, x0s[1])
    np.testing.assert_allclose(np.asarray(infos.x[1]), np.asarray(single_infos.x), atol=1e-8)
    assert float(m.effort_l1_N_s[1]) == pytest.approx(float(single_m.effort_l1_N_s), rel=1e-10)


def test_unknown_scenario_is_a_clear_error(capsys):
    assert main(["run", "no-such-scenario"]) == 2
    err = capsys.readouterr().err
    assert "unknown scenario" in err and "fastmpc-3d" in err


def test_list_names_every_scenario(capsys):
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    # one line per scenario, its name as the first word (long names stay separate)
    assert [line.split()[0] for line in out.splitlines()] == list(SCENARIOS)


def test_run_disturbed_json(capsys):
    """`rvdjax run NAME --disturbed --seed S`: noise and thrust error from PRNG key S; the
    JSON says so and lists the disturbance assumptions."""
    import json

    assert main(["run", "rotating-target-a", "--disturbed", "--seed", "4", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["disturbed"] is True and out["seed"] == 4
    assert out["docked"] is True and np.isfinite(out["effort_l1_N_s"])
    assert any("Gauss-Markov" in a for a in out["assumptions"])


def test_run_command_json_and_plot(capsys, tmp_path):
    plot = tmp_path / "run.png"
    assert main(["run", "fastmpc-3d", "--json", "--plot", str(plot)]) == 0
    import json

    out = json.loads(capsys.readouterr().out)
    for key in (
        "scenario",
        "docked",
        "delta_v_m_s",
        "total_impulse_N_s",
        "effort_l1_N_s",
        "time_to_dock_s",
        "max_violation_m",
        "solver_status_counts",
        "mean_solve_ms",
        "published",
        "assumptions",
    ):
        assert key in out, key
    assert out["scenario"] == "fastmpc-3d" and out["docked"] is True
    assert all(abs(c["rel_diff"]) < 0.15 for c in out["comparison"])
    assert plot.stat().st_size > 10_000 and plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize(
    "change, word",
    [
        (dict(mass=-1.0), "mass"),
        (dict(ts=0.0), "ts"),
        (dict(stop_radius=-2.3), "stop_radius"),
        (dict(u_max=jnp.array([20.0, 0.0, 20.0])), "u_max"),
        (dict(R=-jnp.eye(3)), "R must be positive definite"),
        (dict(radii=jnp.array([20.0, -1.0])), "radii"),
    ],
)
def test_bad_loop_parameters_raise(change, word):
    with pytest.raises(ValueError, match=word):
        validate_loop(PARAMS._replace(**change), X0)


def test_start_inside_keepout_raises():
    inside = np.asarray(PARAMS.obstacles[0, :3]) + np.array([1.0, 0.0, 0.0])
    x0 = np.concatenate([inside, np.zeros(3)])
    with pytest.raises(ValueError, match="inside keep-out zone 1"):
        validate_loop(PARAMS, x0)
    with pytest.raises(ValueError, match="x0 contains NaN"):
        validate_loop(PARAMS, np.full(6, np.nan))
    validate_loop(PARAMS, X0)  # the scenario itself is fine


def test_nonlinear_truth_two_body_j2(accurate_run):
    """Model mismatch: CW plans flown on a two-body + J2 truth still dock, at nearly the same
    cost; the plans graze the keep-out spheres, so the mismatch pushes the truth inside by
    micrometres (measured 6e-5 m)."""
    config = dataclasses.replace(CONFIGS["accurate"], truth="two-body-j2")
    validate_loop(PARAMS, X0, config)
    infos, m = jax.jit(lambda p, x: run_closed_loop(p, x, config))(PARAMS, X0)
    _, m_lin = accurate_run
    assert bool(m.docked)
    assert float(m.max_violation_m) <= 1e-3
    assert abs(float(m.effort_l1_N_s) / float(m_lin.effort_l1_N_s) - 1.0) < 0.01
    x_lin = np.asarray(accurate_run[0].x)
    assert np.max(np.abs(np.asarray(infos.x)[:50, :3] - x_lin[:50, :3])) > 1e-6  # truth differs


def test_nonlinear_truth_needs_an_orbit():
    config = dataclasses.replace(CONFIGS["accurate"], truth="two-body")
    with pytest.raises(ValueError, match="orbit"):
        validate_loop(PARAMS._replace(orbit=None), X0, config)
    with pytest.raises(ValueError, match="truth"):
        dataclasses.replace(CONFIGS["accurate"], truth="n-body")


def test_closed_loop_gradient_matches_central_differences():
    """The closed loop is differentiable: d(loss)/d(log R scale, log Q scale) through 12 MPC
    steps (implicit derivative of every solve, lax.scan) against central differences."""
    free, x0 = SCENARIOS["fastmpc-3d-free"].build()
    config = dataclasses.replace(CONFIGS["accurate"], n_steps=12)

    def loss(theta):
        q = free._replace(R=free.R * jnp.exp(theta[0]), Q=free.Q * jnp.exp(theta[1]))
        infos, _ = run_closed_loop(q, x0, config)
        return 1e-3 * jnp.sum(infos.u**2) + 1e-6 * jnp.sum(infos.x[-1, :3] ** 2)

    g = np.asarray(jax.jit(jax.grad(loss))(jnp.zeros(2)))
    f = jax.jit(loss)
    h = 1e-4
    fd = np.array([(f(h * e) - f(-h * e)) / (2 * h) for e in np.eye(2)])
    assert np.all(np.abs(g) > 1e-4)  # both weights move the loss
    np.testing.assert_allclose(g, fd, rtol=1e-5)
