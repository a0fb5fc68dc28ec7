"""The three-phase family (paper 003 Sec. 3.6) through the closed-loop kernel."""

from __future__ import annotations

import dataclasses
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flights import flight

from rvdjax.constraints import margins
from rvdjax.families import phases as ph
from rvdjax.loop.engine import EngineConfig, arrays_source, run_batch
from rvdjax.scenarios import SCENARIOS
from rvdjax.scenarios import paper003 as thesis
from rvdjax.solver import Status, solve
from rvdjax.solver.barrier import rows_of

CASES = ("vbar", "rbar", "rotating")
# the Table 3.6 variant without set point differs from V-bar only in traced data: same program
RUNS = CASES + ("vbar-nosetpoint",)
ENTRY_STEPS = 6  # docking-phase steps (30 s) allowed for the entry transient


@pytest.fixture(scope="module")
def runs():
    """The three cases and the V-bar case without set point share one program."""
    _, params, infos, m = flight(tuple(f"thesis-{c}" for c in RUNS), n_steps=200)
    return params, infos, m


@pytest.fixture(scope="module")
def lp_run():
    """V-bar with the LP rendezvous (Table 3.6), a leading batch axis of one."""
    _, params, infos, m = flight(("thesis-vbar-lp",), n_steps=150)
    return params, infos, m


@pytest.fixture(params=["runs", "lp_run"])
def any_run(request):
    return request.getfixturevalue(request.param)


def test_every_case_docks_at_the_port(any_run):
    params, infos, m = any_run
    assert np.all(m.docked)
    for i in range(len(m.docked)):
        n = int(infos.active[i].sum())
        # phases run 0 -> 1 -> 2 in order, each visited
        phase = infos.phase[i, :n]
        assert phase[0] == 0 and phase[-1] == 2 and np.all(np.diff(phase) >= 0)
        assert set(phase.tolist()) == {0, 1, 2}
        # time is the sum of the per-step sample times, and of the per-phase times
        assert m.time_to_dock_s[i] == pytest.approx(infos.dt[i, :n].sum())
        assert m.time_to_dock_s[i] == pytest.approx(m.phase_time_s[i].sum())
        assert np.allclose(m.phase_time_s[i] / params.ts[i], np.bincount(phase, minlength=3))
        # the docked state: propagate the last step and compare with the port (r3 = 0.1 m)
        k = 2
        x_end = params.A[i, k] @ infos.x[i, n - 1] + params.B[i, k] @ infos.u[i, n - 1]
        p_i = jax.tree.map(lambda a, i=i: a[i], params)
        port, _, _ = ph.target_state(p_i, m.time_to_dock_s[i])
        assert np.linalg.norm(x_end[:3] - np.asarray(port)) <= float(params.r3[i])
        # rvdjax verify's contact speed: the speed of that docked state
        from rvdjax.verify.requirements import parse_requirement

        req = parse_requirement("contact-speed<=0.1", set(m.margins_m), True)
        margin = float(req.exact(jax.tree.map(lambda a, i=i: a[i], m), "delta_v_m_s"))
        assert margin == pytest.approx(0.1 - np.linalg.norm(x_end[3:]), abs=1e-9)
        # delta-v bookkeeping
        assert m.delta_v_m_s[i] == pytest.approx(m.phase_delta_v_m_s[i].sum())
        assert m.delta_v_m_s[i] <= m.delta_v_l1_m_s[i] <= np.sqrt(3) * m.delta_v_m_s[i]
        assert np.all(np.abs(infos.u[i, :n]) <= params.u_max[i, phase][:, None] + 1e-9)


def test_constraints_of_the_truth(any_run):
    params, infos, m = any_run
    # keep-out sphere (rendezvous) and overshoot plane (approach), judged at the samples and
    # between them, and the docking cone once the chaser has entered it. The keep-out planes
    # also hold between samples in the plans (Config.between_samples): the V-bar runs without
    # set point and with the LP rendezvous, which ride the 100 m sphere, no longer graze it
    # (2.8 and 8.5 cm when only the samples were planned). The docking cone is met at the
    # samples and grazed between them by at most 2 mm (the rotating target's cone turns)
    assert np.all(m.max_violation_m <= 2e-3), m.max_violation_m
    for name in ("keep_out", "overshoot"):
        assert np.all(m.margins_m[name] >= 0.0), (name, m.margins_m[name])
    for i in range(len(m.docked)):
        act = infos.active[i]
        dock_steps = np.flatnonzero(act & (infos.phase[i] == 2))
        settled = dock_steps[ENTRY_STEPS:]
        assert len(settled) > 10
        # after the entry transient: inside the 8 deg docking cone, below v_max at the samples
        # (the margins also hold the states between samples: the cone is checked on the
        # sampled states themselves, and between them within 2 mm)
        p_i = jax.tree.map(lambda a, i=i: a[i], params)
        g2 = ph.Guidance(phase=jnp.asarray(2))
        for k in settled:
            blocks = ph.truth_blocks(p_i, ph.Config(), g2, infos.x[i, k], infos.t[i, k])
            assert np.min(margins(blocks, infos.x[i, k])["docking_cone"]) >= -1e-6
        assert np.min(infos.margins["docking_cone"][i, settled]) >= -2e-3
        speed = np.max(np.abs(infos.x[i, settled, 3:]), axis=-1)  # Eq. 3.13: inf-norm
        assert np.all(speed <= params.v_max[i] + 1e-6)
        # every hard-row violation of a plan is either a planned (not flown) keep-out plane
        # violation far from the sphere, or the docking entry transient. Without set point
        # the chaser is pulled at the sphere and its plans cannot brake in time against the
        # turning planes (<= 4.7 m planned, the closest 38 m from the sphere; the truth stays
        # outside, max_violation_m = 0)
        bad = np.flatnonzero(act & (infos.hard_violation[i] > 1e-6))
        far = bad[infos.phase[i, bad] == 0]
        setpoint = float(params.setpoint[i]) == 1.0
        keep_out = np.linalg.norm(infos.x[i, far, :3], axis=-1) - params.r1[i]  # at the samples
        assert np.all(keep_out > (100.0 if setpoint else 30.0))
        assert np.all(infos.hard_violation[i, far] < 0.1 * keep_out)
        assert set(bad[infos.phase[i, bad] == 2]) <= set(dock_steps[:ENTRY_STEPS])
        assert not np.any(infos.phase[i, bad] == 1)


def test_solver_statuses(any_run):
    _, infos, m = any_run
    counts = m.status_counts
    # every solve met its stopping test (no iteration cap, nothing non-finite) ...
    assert np.all(counts[:, Status.MAX_ITER] == 0) and np.all(counts[:, Status.NONFINITE] == 0)
    raw = np.where(infos.active, infos.solver_status, Status.CONVERGED)
    assert np.all((raw == Status.CONVERGED) | (raw == Status.INFEASIBLE))
    # ... and the remaining INFEASIBLE steps are exactly those with hard-row violations
    infeasible = infos.active & (infos.status == Status.INFEASIBLE)
    assert np.array_equal(infeasible, infos.active & (infos.hard_violation > 1e-6))
    assert np.all(counts[:, Status.INFEASIBLE] <= 15)


def test_compare_with_thesis(runs):
    """Paper 003 Tables 3.3-3.5. Within 15 %: R-bar delta-v and time. V-bar comes out
    ~20 % cheaper and ~17 % faster, the rotating case (assumed rate) ~23 % / ~22 %: not
    asserted (see the module report). The phase structure of the thesis holds in all cases."""
    _, _, m = runs
    i = CASES.index("rbar")
    _, _, dv, tf, _, _ = thesis.CASES["rbar"]
    assert m.delta_v_m_s[i] == pytest.approx(dv, rel=0.15)
    assert m.time_to_dock_s[i] == pytest.approx(tf, rel=0.15)
    for i, case in enumerate(CASES):
        _, _, dv, tf, dv_phase, _ = thesis.CASES[case]
        pdv = m.phase_delta_v_m_s[i]
        # far range dominates the delta-v, final approach is the cheapest phase (< 0.5 m/s)
        assert pdv[0] > pdv[1] > pdv[2] and pdv[2] < 0.5
        assert pdv[0] / pdv.sum() > 0.6
        # same order of magnitude as the thesis: within 30 % on delta-v and time
        assert 0.7 < m.delta_v_m_s[i] / dv < 1.3 and 0.7 < m.time_to_dock_s[i] / tf < 1.3


def test_compare_with_table_3_6(runs, lp_run):
    """Paper 003 Sec. 3.6.4, Table 3.6 (V-bar rendezvous cost variants). Within 15 %: the LP
    maneuver time. Delta-v comes out ~18 % below the thesis in every variant (as for the
    V-bar QP with set point) and the time without set point ~37 % below: not asserted. The
    thesis' qualitative results that hold: without the set point the maneuver takes much
    longer than with it (thesis 2.45x, here 1.9x), so does the LP, and the order of the
    delta-v (no set point < LP < set point) is the thesis' order. With the rendezvous
    keep-out planned between samples (Config.between_samples, which keeps the chaser out of
    the sphere that it grazed by 2.8 cm between samples) the run without set point takes
    45 min instead of 55, about as long as the LP's (thesis: 71 against 41 min)."""
    _, infos, m = runs
    _, lp_infos, lp = lp_run
    qp, nosp = CASES.index("vbar"), RUNS.index("vbar-nosetpoint")
    _, _, dv_lp, tf_lp = thesis.COST_VARIANTS["vbar-lp"]
    assert lp.time_to_dock_s[0] == pytest.approx(tf_lp, rel=0.15)
    t = {"qp": m.time_to_dock_s[qp], "nosp": m.time_to_dock_s[nosp], "lp": lp.time_to_dock_s[0]}
    dv = {"qp": m.delta_v_m_s[qp], "nosp": m.delta_v_m_s[nosp], "lp": lp.delta_v_m_s[0]}
    assert t["nosp"] > 1.5 * t["qp"] and t["lp"] > 1.5 * t["qp"]
    assert dv["nosp"] < dv["lp"] < dv["qp"]
    # same order of magnitude as the thesis: within 30 % on delta-v
    for key, name in (("nosp", "vbar-nosetpoint"), ("lp", "vbar-lp")):
        _, _, dv_t, _ = thesis.COST_VARIANTS[name]
        assert 0.7 < dv[key] / dv_t < 1.3
    # the rendezvous phase stays the dominant one
    assert m.phase_delta_v_m_s[nosp, 0] / dv["nosp"] > 0.6
    assert lp.phase_delta_v_m_s[0, 0] / dv["lp"] > 0.6


@pytest.mark.parametrize("name", ["thesis-vbar", "thesis-vbar-lp"])
def test_the_phase_model_is_the_one_the_ocp_has(name):
    """The fields the batch engine rebuilds from a slot's phase instead of storing them (the
    model A, B, c, Q, R, the linear costs, the input rows, and the state rows' mask and
    penalty, neutralised as the solver's start does) are, bit for bit, those of that phase's
    OCP at any state and time, and the model table's entry that the GPU kernels read is its
    [B, A]; none with the thrusters' finite burns (their B and c follow the plan)."""
    sc = SCENARIOS[name]
    p, x0 = sc.build()
    fc = sc.loop().config.family_config
    g0 = ph.init(p, fc, x0)
    plan = ph.initial_plan(p, fc, g0, x0)

    @jax.jit
    def both(g, x, t):
        ocp = ph.ocp(p, fc, g, x, t, plan)[0]
        fields = ph.model(p, fc, g)
        return ocp, rows_of(ocp).rho, dict(fields, table=fields["table"]())

    states = [(x0, 100.0), (0.3 * x0[::-1], 2500.0)]
    for phase, (x, t) in itertools.product(range(3), states):
        ocp, rho, fields = both(g0._replace(phase=jnp.asarray(phase, jnp.int32)), x, t)
        table = fields.pop("table")
        assert set(fields) == {"A", "B", "c", "Q", "R", "q", "r", "Fu", "fu", "x_mask", "rho"}
        assert 0 < np.sum(np.asarray(ocp.x_mask)) < np.size(ocp.x_mask)
        assert np.shape(table.M)[0] == 3 and int(table.index) == phase
        BA = np.concatenate([np.asarray(ocp.B), np.asarray(ocp.A)], axis=-1)
        np.testing.assert_array_equal(np.asarray(table.M)[phase], BA)
        for field, want in (("Fu", ocp.Fu), ("x_mask", ocp.x_mask), ("rho", rho)):
            np.testing.assert_array_equal(np.asarray(getattr(table, field))[phase], want)
        for field, a in fields.items():
            want = rho if field == "rho" else getattr(ocp, field)
            np.testing.assert_array_equal(np.asarray(a), np.asarray(want), field)
    with_burns, _ = sc.build(thrusters=True)
    assert ph.model(with_burns, fc, g0) is None
    assert ph.model(with_burns, dataclasses.replace(fc, finite_burn=False), g0) is not None


def test_the_engine_flies_the_cases_as_single_flights(runs):
    """The four cases through the batch engine (per-run parameters, two slots, so that runs
    in different phases share a batch; the model rebuilt from each slot's phase) land as
    their single flights: the same steps, phase times and statuses, delta-v to rounding."""
    params, _, m = runs
    x0s = jnp.stack([SCENARIOS[f"thesis-{c}"].build()[1] for c in RUNS])
    loop = SCENARIOS["thesis-vbar"].loop("accurate", n_steps=200)
    out = run_batch(
        loop, arrays_source(x0s, params=params), len(RUNS), config=EngineConfig(slots=2, chunk=2)
    )
    e = out["metrics"]
    np.testing.assert_array_equal(e.steps, m.steps)
    np.testing.assert_array_equal(e.phase_time_s, m.phase_time_s)
    np.testing.assert_array_equal(e.status_counts, m.status_counts)
    np.testing.assert_allclose(e.delta_v_m_s, m.delta_v_m_s, rtol=1e-9)


@pytest.mark.slow  # 14 s; `pytest -m slow`
def test_padding_equals_unpadded_phase():
    """A docking-phase OCP (N3 = 12) padded to 30 stages with identity dynamics and zero cost
    has the same solution as the unpadded one."""
    p, x0 = SCENARIOS["thesis-vbar"].build()
    x = jnp.array([0.4, 9.0, 0.5, 0.01, -0.05, 0.0])
    t, g = jnp.asarray(100.0), ph.Guidance(phase=jnp.asarray(2))
    padded, _ = ph.ocp(p, ph.Config(N=(30, 15, 12)), g, x, t, None)
    plain, _ = ph.ocp(p, ph.Config(N=(12, 12, 12)), g, x, t, None)
    assert padded.N == 30 and plain.N == 12
    sp, s0 = solve(padded), solve(plain)
    assert int(sp.status) == Status.CONVERGED and int(s0.status) == Status.CONVERGED
    assert np.allclose(sp.u[:12], s0.u, atol=1e-6)
    assert np.allclose(sp.x[:12], s0.x, atol=1e-5)
    assert np.allclose(sp.x[12:], sp.x[11], atol=1e-5)  # padded stages hold x_N
    assert np.allclose(sp.objective, s0.objective, rtol=1e-6)


@pytest.mark.parametrize(
    "over, match",
    [
        (dict(ts=(30.0, 0.0, 5.0)), "ts"),
        (dict(ts=(30.0, 20.0, -5.0)), "ts"),
        (dict(ts=(30.0, 20.0)), "one value per phase"),
        (dict(mass=0.0), "mass"),
        (dict(mass=-14.0), "mass"),
        (dict(r1=-100.0), "r1"),
        (dict(r2=-1.0), "r2"),
        (dict(r3=0.0), "r3"),
        (dict(r2=200.0), "r3 < r2 < r1"),
        (dict(v_max=0.0), "v_max"),
        (dict(u_max=(0.1, 0.1, 0.0)), "u_max"),
        (dict(los_deg=(15.0, 90.0, 8.0)), "los_deg"),
        (dict(altitude_m=-1.0), "altitude_m"),
        (dict(R=(np.eye(3), np.eye(3), -np.eye(3))), r"R\[2\]"),
        (dict(port_body=(0.0, 0.0, 0.0)), "port_body"),
        (dict(x0=(10.0, 0.0, 0.0, 0.0, 0.0, 0.0)), "keep-out"),
        (dict(switch_tol=1.5), "switch_tol"),
        (dict(cd_chaser=0.0), "cd_chaser"),
        (dict(inclination_deg=200.0), "inclination_deg"),
    ],
)
def test_bad_inputs(over, match):
    with pytest.raises(ValueError, match=match):
        SCENARIOS["thesis-vbar"].build(**over)


def test_bad_config():
    with pytest.raises(ValueError, match="N"):
        ph.Config(N=(30, 0, 12))
    with pytest.raises(ValueError, match="N"):
        ph.Config(N=(30, 15))
    with pytest.raises(ValueError, match="rendezvous_cost"):
        ph.Config(rendezvous_cost="l2")
    with pytest.raises(ValueError, match="n_steps"):
        SCENARIOS["thesis-vbar"].loop(n_steps=0)
    with pytest.raises(ValueError, match="truth"):
        SCENARIOS["thesis-vbar"].loop(truth="sgp4")


def test_scenario_records():
    names = {n for n, sc in SCENARIOS.items() if sc.source.startswith("paper 003")}
    assert names == {
        "thesis-vbar",
        "thesis-rbar",
        "thesis-rotating",
        "thesis-vbar-nosetpoint",
        "thesis-vbar-lp",
    }
    assert SCENARIOS["thesis-vbar-nosetpoint"].published == {
        "delta_v_m_s": {"thesis": 12.65},
        "time_to_dock_s": {"thesis": 71.23 * 60},
    }
    assert SCENARIOS["thesis-vbar-lp"].published == {
        "delta_v_m_s": {"thesis": 12.74},
        "time_to_dock_s": {"thesis": 40.57 * 60},
    }
    for name in ("thesis-vbar-nosetpoint", "thesis-vbar-lp"):
        assert len(SCENARIOS[name].assumptions) > len(SCENARIOS["thesis-vbar"].assumptions)
    assert float(SCENARIOS["thesis-vbar-nosetpoint"].build()[0].setpoint) == 0.0
    lp = SCENARIOS["thesis-vbar-lp"]
    assert lp.loop().config.family_config.rendezvous_cost == "lp"
    assert lp.loop().config.settings.max_iter == 300
    sc = SCENARIOS["thesis-vbar"]
    assert sc.published == {"delta_v_m_s": {"thesis": 13.28}, "time_to_dock_s": {"thesis": 1744.0}}
    # the LP cost needs a diagonal rendezvous R
    params, x0 = lp.build()
    bad = params._replace(R=params.R.at[0, 0, 1].set(1.0).at[0, 1, 0].set(1.0))
    with pytest.raises(ValueError, match="diagonal"):
        lp.check(bad, x0, lp.loop())


def test_nonlinear_truth_with_j2_and_drag():
    """V-bar flown against the two-body + J2 + drag truth (model mismatch, as paper 003 Ch. 5):
    it still docks without violating the keep-out or overshoot constraints, and the loop's
    truth is exactly what :func:`rvdjax.propagate.propagate_relative` gives for the logged
    impulses (applied at the step start, then a coast of Ts)."""
    from rvdjax.propagate import propagate_relative

    loop, params, infos, m = flight(("thesis-vbar",), n_steps=200, truth="two-body-j2-drag")
    params, infos, m = jax.tree.map(lambda a: a[0], (params, infos, m))
    assert bool(m.docked) and float(m.max_violation_m) == 0.0
    orbit, x = params.plant.orbit, np.asarray(infos.x[0])
    for k in range(3):
        dv, ts = np.asarray(infos.u[k]), float(infos.dt[k])
        x_kick = x.copy()
        x_kick[3:] += dv
        orbit, x = propagate_relative(
            orbit,
            x_kick,
            np.zeros(3),
            14.0,
            ts,
            loop.config.truth_substeps,
            j2=True,
            drag=params.plant.drag,
        )
        x = np.asarray(x)
        np.testing.assert_allclose(np.asarray(infos.x[k + 1]), x, rtol=0, atol=1e-9)
    # the CW prediction of the same step misses the truth by a measurable amount
    cw = np.asarray(params.A[0] @ infos.x[0] + params.B[0] @ infos.u[0])
    assert 1e-4 < np.linalg.norm(cw[:3] - np.asarray(infos.x[1, :3])) < 10.0


def test_keep_out_planes_turn_with_the_natural_motion():
    """Paper 003 Sec. 3.1.3: a rotation that does not fit in the horizon at the capped rate
    turns the way the chaser's bearing is already turning (the long way round if need be);
    one that fits takes the shortest path."""
    import jax.numpy as jnp

    r0 = jnp.array([0.0, -1000.0, 0.0])
    a_final = jnp.array([1.0, 0.0, 0.0])  # 90 deg away, the short way through +x
    slow, fast = 1e-4, 1.0  # rad/s: 30 stages x 30 s x 1e-4 = 0.09 rad < pi / 2
    for v0, sign in ((jnp.array([1.0, 0.0, 0.0]), 1.0), (jnp.array([-1.0, 0.0, 0.0]), -1.0)):
        n = np.asarray(ph._plane_normals(r0, a_final, 30, 30, 30.0, slow, v0))
        assert np.all(sign * n[:, 0] > 0)  # turning towards +x (with the motion) or -x
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
        # rate cap: consecutive normals at most rate * ts apart
        ang = np.arccos(np.clip(np.sum(n[1:] * n[:-1], axis=1), -1, 1))
        assert np.all(ang <= slow * 30.0 + 1e-12)
        n_fast = np.asarray(ph._plane_normals(r0, a_final, 30, 30, 30.0, fast, v0))
        np.testing.assert_allclose(n_fast[-1], np.asarray(a_final), atol=1e-12)
        assert np.all(n_fast[:, 0] >= -1e-12)  # fits: the short way whatever the motion


def test_latched_turn_keeps_its_sense_through_the_antipode():
    """Config.latch_turn: near the bearing opposite the approach axis the tangential velocity
    (and the shortest turn's direction) flip from step to step; the unlatched planes flip
    with them, the latched ones keep turning about the axis chosen first. The update latches
    the axis while the rotation does not fit and clears it once it fits."""
    import dataclasses

    a_final = jnp.array([0.0, 1.0, 0.0])  # V-bar approach axis
    rate, ts, n = 1.1e-3, 30.0, 30  # 0.99 rad a horizon: half a turn does not fit
    # the chaser just either side of the antipode (bearing 270 deg), its bearing turning
    # once clockwise, once anticlockwise: the short way swaps sides, and so does the motion
    sides = [(jnp.array([-5.0, -1000.0, 0.0]), jnp.array([0.1, 0.0, 0.0])),
             (jnp.array([5.0, -1000.0, 0.0]), jnp.array([-0.1, 0.0, 0.0]))]  # fmt: skip
    first = np.asarray(ph._plane_normals(sides[0][0], a_final, n, n, ts, rate, sides[0][1]))
    second = np.asarray(ph._plane_normals(sides[1][0], a_final, n, n, ts, rate, sides[1][1]))
    assert first[-1, 0] > 0 > second[-1, 0]  # unlatched: the planes swing to the other side
    u0, w, _, fits = ph._turn(sides[0][0], a_final, n, ts, rate, sides[0][1])
    assert not bool(fits)
    axis = np.cross(np.asarray(u0), np.asarray(w))
    latched = np.asarray(
        ph._plane_normals(sides[1][0], a_final, n, n, ts, rate, sides[1][1], jnp.asarray(axis))
    )
    assert latched[-1, 0] > 0  # latched: still turning the first way
    np.testing.assert_allclose(np.linalg.norm(latched, axis=1), 1.0, atol=1e-12)
    # the family's update latches that axis, and clears it once the rotation fits
    p, _ = SCENARIOS["thesis-vbar"].build()
    p = p._replace(n=jnp.asarray(rate))
    fc = dataclasses.replace(ph.Config(), latch_turn=True)
    x = jnp.concatenate(sides[0])
    g = ph.init(p, fc, x)
    assert np.all(np.asarray(g.turn) == 0)
    samples = (jnp.zeros(8),)
    g1 = ph.update(p, fc, g, x, jnp.zeros(3), x, jnp.asarray(0.0), p.ts[0], samples)[0]
    np.testing.assert_allclose(np.asarray(g1.turn), axis / np.linalg.norm(axis), atol=1e-12)
    near = jnp.array([0.0, 500.0, 0.0, 0.0, 0.0, 0.0])  # on the axis: the rotation fits
    g2 = ph.update(p, fc, g1, near, jnp.zeros(3), near, jnp.asarray(0.0), p.ts[0], samples)[0]
    assert np.all(np.asarray(g2.turn) == 0)
    assert ph.init(p, ph.Config(), x).turn is None  # off: the loop carries nothing new


@pytest.mark.slow  # two 300-step flights of their own programs; `pytest -m slow`
def test_latched_turn_removes_a_deep_breach_of_the_reference():
    """A start inside one of thesis-vbar's breach slabs under paper 003's initial states (the
    middle of a slab 0.04 sigma wide, next to the reference's 30.7 m breach): the per-step
    sense of turn flies it 20+ m into the keep-out sphere; latched, the same start stays out."""
    from rvdjax.loop import fly
    from rvdjax.verify.evaluate import ProblemSpec, problem_for

    pb = problem_for(ProblemSpec("thesis-vbar", "keep-out", "paper003"))
    xi = np.array([1.01540886, 1.34767128, -1.38671643, -0.10798368 + 0.07, 1.03272868])
    lay = pb.scenario.guidance_family.layout
    x0, p = pb.dispersion.apply(jnp.asarray(xi), jnp.asarray(pb.x0), pb.params, lay)
    clearance = {}
    for latch in (False, True):
        loop = pb.scenario.loop(latch_turn=latch)
        _, m = jax.jit(lambda p, x0, loop=loop: fly(loop, p, x0, pb.key, pb.sp))(p, x0)
        clearance[latch] = float(pb.requirement.exact(m, pb.effort_key))
    assert clearance[False] < -20.0, clearance
    assert clearance[True] > 0.0, clearance


def test_keep_out_rows_between_samples_are_the_coasted_states():
    """Config.between_samples: the rendezvous keep-out rows at j Ts / 8 act on x_{t+1} through
    the coast back e^{-Ac (Ts - tau_j)} (SciPy's expm), and their slack is the plane's slack at
    the state the chaser coasted through (an impulsive delta-v at the step start)."""
    from scipy.linalg import expm

    from rvdjax.constraints import between_samples, block_margin, keep_out_plane

    p, _ = SCENARIOS["thesis-vbar"].build()
    Ac, ts = np.asarray(p.plant.Ac), float(p.ts[0])
    back = np.asarray(ph._coast_back(p.plant.Ac, p.ts[0]))
    taus = ts * np.arange(1, ph.SUBSAMPLES) / ph.SUBSAMPLES
    for j, tau in enumerate(taus):
        np.testing.assert_allclose(back[j], expm(-Ac * (ts - tau)), rtol=0, atol=1e-12)
    rng = np.random.default_rng(1)
    x_plus = np.array([300.0, -200.0, 20.0, 0.4, 0.6, 0.0])  # just after the impulse
    x_next = expm(Ac * ts) @ x_plus
    n = rng.normal(size=(1, 3))
    n /= np.linalg.norm(n)
    plane = keep_out_plane(jnp.asarray(n), 100.0, 6, (0, 1, 2))
    rows = between_samples(plane, back)
    slack = np.asarray(block_margin(rows, jnp.asarray(x_next)))[0]
    states = [expm(Ac * tau) @ x_plus for tau in taus]
    expected = [float(n[0] @ s[:3] - 100.0) for s in states]
    np.testing.assert_allclose(slack, expected, atol=1e-9)
