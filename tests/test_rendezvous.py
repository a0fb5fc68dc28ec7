"""The rendezvous family on fastmpc-3d (paper 000 Sec. IV.A) through the closed-loop kernel."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flights import first, flight

from rvdjax.families import rendezvous as rv
from rvdjax.loop import fly
from rvdjax.loop.plant import with_plant
from rvdjax.loop.reference import reference_loop
from rvdjax.scenarios import SCENARIOS, get_scenario
from rvdjax.scenarios.paper000 import FASTMPC3D, FASTMPC3D_X0
from rvdjax.solver import Status

SC = get_scenario("fastmpc-3d")
PAPER_IMPULSE_KN_S = SC.published["effort_l1_N_s"]["Fast MPC"] / 1e3


@pytest.fixture(scope="module")
def accurate_run():
    """fastmpc-3d and fastmpc-3d-free share one program (only the traced mask differs)."""
    loop, params, infos, m = flight(("fastmpc-3d", "fastmpc-3d-free"))
    return loop, first(params), first(infos), first(m)


def test_fastmpc3d_docks_without_violation(accurate_run):
    _, params, infos, m = accurate_run
    n = int(np.sum(infos.active))
    assert bool(m.docked) and int(m.steps) == n
    assert np.linalg.norm(infos.x[n - 1, :3]) > float(params.stop_radius)  # last active step
    assert float(m.max_violation_m) <= 1e-6
    assert float(m.margins_m["keep_out"]) >= -1e-6  # the truth never enters a sphere ...
    assert float(m.margins_m["keep_out"]) < 1.0  # ... but the plans ride them (rows binding)
    counts = np.asarray(m.status_counts)
    assert counts[Status.CONVERGED] == n and counts[1:].sum() == 0
    assert int(np.asarray(m.iteration_histogram).sum()) == n
    for leaf in jax.tree.leaves(infos):  # no NaN anywhere in the record
        assert not np.any(np.isnan(np.asarray(leaf, dtype=float)))


def test_fastmpc3d_total_impulse_matches_paper(accurate_run):
    """Paper 000: Fast MPC 33.98 kN s (ISNM 33.80, IPOPT NMPC 32.93, fmincon 34.33).
    Measured: 33.46 kN s (L1 sum), -1.5 %. Asserted: within 15 %."""
    _, _, _, m = accurate_run
    ours = float(m.effort_l1_N_s) / 1e3
    assert abs(ours - PAPER_IMPULSE_KN_S) / PAPER_IMPULSE_KN_S < 0.15
    l2 = float(m.total_impulse_N_s) / 1e3  # L2 <= L1 <= sqrt(3) L2 (three axes)
    assert l2 <= ours <= np.sqrt(3) * l2 + 1e-9
    assert float(m.delta_v_m_s) == pytest.approx(float(m.total_impulse_N_s) / 6500.0)


def test_metrics_are_the_reduction_of_the_steps(accurate_run):
    """The one metrics reduction agrees with the per-step record."""
    _, params, infos, m = accurate_run
    act = infos.active
    ts = float(params.ts)
    np.testing.assert_allclose(infos.dt[act], ts)
    assert float(m.time_to_dock_s) == pytest.approx(act.sum() * ts)
    effort = np.sum(np.abs(infos.u[act])) * ts
    assert float(m.effort_l1_N_s) == pytest.approx(effort, rel=1e-12)
    worst = np.min(np.where(act[:, None], infos.margins["keep_out"], np.inf))
    assert float(m.margins_m["keep_out"]) == pytest.approx(worst)


def test_same_trajectory_as_clarabel_from_python(accurate_run):
    """The same step driven from Python with Clarabel solving every QP flies the same path."""
    loop, params, infos, m = accurate_run
    ref_infos, ref_m, _ = reference_loop(loop, params, np.asarray(FASTMPC3D_X0))
    n = len(ref_infos)
    assert n == int(np.sum(infos.active)) and bool(ref_m.docked)
    x_ref = np.stack([i.x for i in ref_infos])
    u_ref = np.stack([i.u for i in ref_infos])
    assert np.max(np.abs(infos.x[:n, :3] - x_ref[:, :3])) <= 1e-3  # measured 5e-5 m
    assert np.max(np.abs(infos.u[:n] - u_ref)) <= 1e-3 * FASTMPC3D["u_max"]
    assert float(ref_m.effort_l1_N_s) == pytest.approx(float(m.effort_l1_N_s), rel=1e-6)


def test_obstacle_free_variant_and_batch(accurate_run):
    """vmap over initial conditions equals single runs."""
    loop, params, infos, m = flight(("fastmpc-3d", "fastmpc-3d-free"))
    free = first(params, 1)
    assert float(free.obstacle_mask.sum()) == 0.0 and bool(m.docked[1])
    assert np.all(np.isinf(infos.margins["keep_out"][1]))  # switched off: no margin counted
    single_infos, single_m = jax.jit(lambda p, x: fly(loop, p, x))(free, FASTMPC3D_X0)
    np.testing.assert_allclose(infos.x[1], np.asarray(single_infos.x), atol=1e-8)
    assert float(m.effort_l1_N_s[1]) == pytest.approx(float(single_m.effort_l1_N_s), rel=1e-10)


def test_nonlinear_truth_two_body_j2(accurate_run):
    """Model mismatch: CW plans flown on a two-body + J2 truth still dock, at nearly the same
    cost; the plans graze the keep-out spheres, so the mismatch can push the truth inside by
    micrometres."""
    _, loop_infos, m_lin = accurate_run[0], accurate_run[2], accurate_run[3]
    _, _, infos, m = flight(("fastmpc-3d",), truth="two-body-j2")
    m, infos = first(m), first(infos)
    assert bool(m.docked)
    assert float(m.max_violation_m) <= 1e-3
    assert abs(float(m.effort_l1_N_s) / float(m_lin.effort_l1_N_s) - 1.0) < 0.01
    assert np.max(np.abs(infos.x[:50, :3] - loop_infos.x[:50, :3])) > 1e-6  # truth differs


@pytest.mark.parametrize(
    "change, word",
    [
        (dict(mass=-1.0), "mass"),
        (dict(ts=0.0), "ts"),
        (dict(stop_radius=-2.3), "stop_radius"),
        (dict(u_max=(20.0, 0.0, 20.0)), "u_max"),
        (dict(R=(100.0, -1.0, 100.0)), "R must be positive definite"),
        (dict(radii=(20.0, -1.0)), "radii"),
        (dict(Q=(1.0,) * 5), "Q must have shape"),
        (dict(x0=(np.nan,) * 6), "x0 must be finite"),
        (dict(x0=(-30.0, -801.0, 10.0, 0.0, 0.0, 0.0)), "inside keep-out zone 1"),
        (dict(x0=(1.0, 0.0, 0.0, 0.0, 0.0, 0.0)), "stop radius"),
    ],
)
def test_bad_parameters_raise(change, word):
    with pytest.raises(ValueError, match=word):
        SC.build(**change)


def test_truth_availability_per_family():
    with pytest.raises(ValueError, match="truth"):
        SC.loop(truth="two-body-j2-drag")  # no drag model for this family
    with pytest.raises(ValueError, match="truth"):
        SCENARIOS["spot-2d-a"].loop(truth="two-body")  # planar test bed: linear only
    params, x0 = SC.build()
    loop = SC.loop(truth="two-body")
    with pytest.raises(ValueError, match="orbit"):
        SC.check(with_plant(params, orbit=None), x0, loop)


def test_closed_loop_gradient_matches_central_differences():
    """The closed loop is differentiable: d(loss)/d(log R scale, log Q scale) through 12 MPC
    steps (implicit derivative of every solve inside the lax.scan) against central
    differences of the loss as differentiation evaluates it (value_and_grad's value: a solve
    under differentiation steps 0.99 of the way to the boundary, docs/solver.md; the plain
    loss differs from it within the solver's tolerance, 3e-5 relative here in the
    difference quotient)."""
    sc = SCENARIOS["fastmpc-3d-free"]
    params, x0 = sc.build()
    loop = sc.loop(n_steps=12)

    def loss(theta):
        p = params._replace(R=params.R * jnp.exp(theta[0]), Q=params.Q * jnp.exp(theta[1]))
        infos, _ = fly(loop, p, x0)
        return 1e-3 * jnp.sum(infos.u**2) + 1e-6 * jnp.sum(infos.x[-1, :3] ** 2)

    g = np.asarray(jax.jit(jax.grad(loss))(jnp.zeros(2)))
    f = jax.jit(lambda theta: jax.value_and_grad(loss)(theta)[0])
    h = 1e-4
    fd = np.array([(f(h * e) - f(-h * e)) / (2 * h) for e in np.eye(2)])
    assert np.all(np.abs(g) > 1e-4)  # both weights move the loss
    np.testing.assert_allclose(g, fd, rtol=1e-5)


def test_family_functions_are_pure_of_arrays():
    """The family's OCP at the first step equals the problem module's first-step OCP."""
    from rvdjax.problems import fastmpc3d_first_step

    params, x0 = SC.build()
    config = rv.Config(N=30)
    g = rv.init(params, config, jnp.asarray(x0))
    ocp, blocks = rv.ocp(
        params, config, g, jnp.asarray(x0), 0.0, rv.initial_plan(params, config, g, jnp.asarray(x0))
    )
    ref = fastmpc3d_first_step()
    for a, b in zip(ocp, ref, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-12)
    assert [b.name for b in blocks] == ["keep_out"]


def test_keep_out_requirement_is_the_smallest_clearance(accurate_run):
    """rvdjax verify's keep-out margin (exact and smooth) on the flown run, against the
    clearances of the moving spheres computed here from the states and times."""
    from rvdjax.verify.requirements import parse_requirement

    loop, params, infos, m = accurate_run
    req = parse_requirement("keep-out", {"keep_out"}, True)
    act = np.asarray(infos.active)
    x, t = np.asarray(infos.x)[act], np.asarray(infos.t)[act]
    obs = np.asarray(params.obstacles)[np.asarray(params.obstacle_mask) > 0]
    radii = np.asarray(params.radii)[np.asarray(params.obstacle_mask) > 0]
    centres = obs[None, :, :3] + t[:, None, None] * obs[None, :, 3:]
    clearance = np.linalg.norm(x[:, None, :3] - centres, axis=-1) - radii
    assert float(req.exact(m, "effort_l1_N_s")) == pytest.approx(clearance.min(), abs=1e-9)
    tau = 1.0
    soft = float(req.smooth(loop, params, infos, m, "effort_l1_N_s", tau))
    assert clearance.min() - tau * np.log(clearance.size) <= soft <= clearance.min() + 1e-12
    assert float(parse_requirement("keep-out>=-3", {"keep_out"}, True).exact(m, "x")) == (
        pytest.approx(clearance.min() + 3.0, abs=1e-9)
    )
