"""Thrusters in the loop: modulation, the truth under valve pulses, one control period end to
end, and closed loops with thrusters (rvdjax.actuators), each against an independent
reference (SciPy's ODE integrator, a tick-by-tick modulator loop, recomputation from the
step records)."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import rvdjax  # noqa: F401  (float64)
from rvdjax.actuators import sets
from rvdjax.actuators.fire import fire
from rvdjax.actuators.modulation import Pulses, delta_sigma, pwm, schmitt
from rvdjax.actuators.response import pulse_response, pulse_segments
from rvdjax.actuators.thrusters import G0, ThrusterSet
from rvdjax.dynamics import cw_continuous, discretize_zoh, mean_motion, planar3dof_continuous
from rvdjax.loop import fly
from rvdjax.loop.plant import truth_step_pulses, with_plant
from rvdjax.propagate import circular_orbit, inertial_to_lvlh, lvlh_basis, lvlh_to_inertial
from rvdjax.scenarios import get_scenario

RNG = np.random.default_rng(7)
_fire = jax.jit(fire, static_argnums=(0, 2))  # (actuation, thrusters, layout, ...)


def _ivp_pulses(Ac, Bc, x0, ts, pulses, g):
    """x(ts) by SciPy's DOP853, integrating between every valve event."""
    Ac, Bc, g = np.asarray(Ac), np.asarray(Bc), np.asarray(g)
    start, width = np.asarray(pulses.start), np.asarray(pulses.width)
    events = np.unique(
        np.clip(np.concatenate([[0.0, ts], start.ravel(), (start + width).ravel()]), 0, ts)
    )
    x = np.asarray(x0, float)
    for a, b in zip(events[:-1], events[1:], strict=True):
        if b - a <= 0:
            continue
        mid = 0.5 * (a + b)
        on = (start <= mid) & (mid < start + width)  # (T, P)
        u = on.sum(axis=1).astype(float) @ g
        sol = solve_ivp(
            lambda t, y, u=u: Ac @ y + Bc @ u, (a, b), x, method="DOP853", rtol=1e-12, atol=1e-14
        )
        x = sol.y[:, -1]
    return x


@pytest.mark.parametrize("model", ["cw", "planar"])
def test_pulse_response_equals_an_ode_integration(model):
    if model == "cw":
        Ac, Bc = cw_continuous(mean_motion(altitude_m=500e3), 14.0)
        nu, ts = 3, 30.0
    else:
        Ac, Bc = planar3dof_continuous(16.9, 0.27)
        nu, ts = 3, 2.0
    T, P = 6, 4
    # disjoint pulses per thruster: cut points sorted, every other interval open
    cuts = np.sort(RNG.uniform(0, ts, (T, 2 * P)), axis=1)
    start, width = cuts[:, 0::2], cuts[:, 1::2] - cuts[:, 0::2]
    width[0] = 0.0  # a thruster that does not fire
    pulses = Pulses(jnp.asarray(start), jnp.asarray(width))
    g = RNG.normal(size=(T, nu))
    x0 = RNG.normal(size=6)
    Ad = jax.scipy.linalg.expm(Ac * ts)
    ours = np.asarray(Ad @ x0 + pulse_response(Ac, Bc, ts, pulses, jnp.asarray(g)))
    ref = _ivp_pulses(Ac, Bc, x0, ts, pulses, g)
    np.testing.assert_allclose(ours, ref, rtol=1e-9, atol=1e-11 * np.abs(ref).max())
    # whole ticks of one shared grid (delta-sigma) by the grid's matrix product
    K = 20
    on = (RNG.uniform(size=(T, K)) < 0.4).astype(float)
    ticks = Pulses(jnp.broadcast_to(jnp.arange(K) * ts / K, (T, K)), jnp.asarray(on * ts / K))
    np.testing.assert_allclose(
        pulse_response(Ac, Bc, ts, ticks, jnp.asarray(g), grid=True),
        _ivp_pulses(Ac, Bc, np.zeros(6), ts, ticks, g),
        rtol=1e-9,
        atol=1e-12,
    )
    # a pulse held over the whole period is the zero-order hold
    full = Pulses(jnp.zeros((1, 1)), jnp.full((1, 1), ts))
    u = RNG.normal(size=(1, nu))
    _, Bd = discretize_zoh(Ac, Bc, ts)
    ref = np.asarray(Bd @ u[0])
    np.testing.assert_allclose(
        pulse_response(Ac, Bc, ts, full, jnp.asarray(u)),
        ref,
        rtol=1e-12,
        atol=1e-13 * np.linalg.norm(ref),
    )


@pytest.mark.parametrize("align", ["start", "centre"])
def test_nonlinear_truth_segments_equal_an_ode_integration(align):
    """Two-body truth under PWM pulses (segments between valve events, RK4) against SciPy
    integrating both bodies inertially with the thrust rotated into LVLH at every instant."""
    from rvdjax.propagate import MU_EARTH  # noqa: F401

    orbit = circular_orbit(500e3)
    ts, mass = 30.0, 14.0
    T = 6
    width = np.array([3.0, 0.0, 7.5, 12.25, 0.02, 30.0])
    start = np.zeros(T) if align == "start" else 0.5 * (ts - width)
    pulses = Pulses(jnp.asarray(start[:, None]), jnp.asarray(width[:, None]))
    g = RNG.normal(size=(T, 3)) * 0.5
    x0 = np.array([100.0, -800.0, 20.0, -0.1, 0.3, 0.01])

    class P:
        pass

    params = P()
    params.mass = mass
    params.drag = None
    x1, _ = truth_step_pulses(
        "two-body",
        40,
        None,
        params,
        orbit,
        jnp.asarray(x0),
        pulses,
        jnp.asarray(g),
        ts,
        from_start=align == "start",
    )

    rc, vc = lvlh_to_inertial(orbit, jnp.asarray(x0))
    y0 = np.concatenate([orbit.r, orbit.v, rc, vc])

    def rhs(t, y):
        rt, vt, r, v = y[:3], y[3:6], y[6:9], y[9:]
        on = ((t >= start) & (t < start + width)).astype(float)
        f_lvlh = on @ g
        R, _ = lvlh_basis(jnp.asarray(rt), jnp.asarray(vt))
        a_t = -3.986004418e14 * rt / np.linalg.norm(rt) ** 3
        a_c = -3.986004418e14 * r / np.linalg.norm(r) ** 3 + np.asarray(R) @ f_lvlh / mass
        return np.concatenate([vt, a_t, v, a_c])

    events = np.unique(np.concatenate([[0.0, ts], start, start + width]))
    y = y0
    for a, b in zip(events[:-1], events[1:], strict=True):
        if b > a:
            y = solve_ivp(rhs, (a, b), y, method="DOP853", rtol=1e-12, atol=1e-9).y[:, -1]
    from rvdjax.propagate import Orbit

    ref = np.asarray(
        inertial_to_lvlh(
            Orbit(jnp.asarray(y[:3]), jnp.asarray(y[3:6])), jnp.asarray(y[6:9]), jnp.asarray(y[9:])
        )
    )
    np.testing.assert_allclose(np.asarray(x1), ref, rtol=0, atol=1e-6)
    # segments: durations add up to the period and every force is the sum of the open thrusters
    d, f = pulse_segments(pulses, jnp.asarray(g), ts, from_start=align == "start")
    assert float(jnp.sum(d)) == pytest.approx(ts)
    # the impulse of the segments is every pulse's
    np.testing.assert_allclose(d @ f, width @ g, atol=1e-12)


def test_centred_pulses_meet_the_zero_order_hold():
    """PWM centred in the period: for the planar double integrator the state at the period's
    end equals the zero-order-hold model's for the mean force, whatever the widths; pulses
    from the period's start miss it by dv (Ts - w) / 2."""
    Ac, Bc = planar3dof_continuous(10.0, 0.15)
    ts = 2.0
    demand = jnp.asarray(RNG.uniform(0.0, ts, 8))
    centred, _, _ = pwm(demand, ts, 1e-6, 0.0, jnp.zeros(8), carry=False, align="centre")
    early, _, _ = pwm(demand, ts, 1e-6, 0.0, jnp.zeros(8), carry=False)
    w = np.asarray(centred.width[:, 0])
    np.testing.assert_allclose(np.asarray(centred.start[:, 0]), 0.5 * (ts - w), atol=1e-14 * ts)
    np.testing.assert_array_equal(np.asarray(early.width), np.asarray(centred.width))
    g = RNG.normal(size=(8, 3)) * 0.15
    _, Bd = discretize_zoh(Ac, Bc, ts)
    mean = w @ g / ts
    ref = np.asarray(Bd @ mean)
    ours = np.asarray(pulse_response(Ac, Bc, ts, centred, jnp.asarray(g)))
    np.testing.assert_allclose(ours, ref, atol=1e-12)
    lag = np.asarray(pulse_response(Ac, Bc, ts, early, jnp.asarray(g))) - ref
    assert np.max(np.abs(lag[:2])) > 1e-3  # the start-aligned pulses are ahead of the model


def test_separate_allocation_is_a_pure_force_plus_a_pure_couple(docking_layout):
    """allocation='separate': the wrench is delivered, and the thrust is the pairs' |Fx| + |Fy|
    plus the least-thrust pure couple (SciPy's linprog), never less than the joint LP's."""
    from scipy.optimize import linprog

    from rvdjax.actuators.thrusters import effectiveness

    base = sets.POSEIDYN_PWM.replace(valve_s=1e-6, min_on_s=0.0)
    joint = base.actuation()
    sep = base.replace(allocation="separate").actuation()
    thr = base.build()
    M = np.asarray(effectiveness(thr.position, thr.direction))[[0, 1, 5]]
    ts = 2.0
    for _ in range(12):
        u = RNG.uniform(-1, 1, 3) * np.array([0.1, 0.1, 0.01])
        args = (thr, docking_layout, jnp.zeros(6), jnp.asarray(u), ts, 10.0, 0.0, jnp.zeros(8))
        out_sep = _fire(sep, *args)
        out_joint = _fire(joint, *args)
        np.testing.assert_allclose(out_sep.u_applied, u, atol=1e-6)
        couple = linprog(np.ones(8), A_eq=M, b_eq=[0.0, 0.0, u[2]], bounds=[(0, 0.15)] * 8)
        assert couple.status == 0
        expected = (abs(u[0]) + abs(u[1]) + couple.fun) * ts
        assert float(out_sep.thrust_impulse) == pytest.approx(expected, rel=1e-5)
        assert float(out_sep.thrust_impulse) >= float(out_joint.thrust_impulse) - 1e-5
    with pytest.raises(ValueError, match="separate"):
        sets.CUBESAT_6U.replace(allocation="separate").actuation()


def test_finite_burn_model_predicts_the_burn():
    """The three-phase model with the thrusters' finite burns (families.phases.finite_burn),
    linearised at the delta-v it is asked for, predicts the truth under the PWM burn from
    the period's start; the impulsive model (paper 003 Eq. 3.1) misses it by m dv^2 / (2 F),
    0.45 m for a 5 s burn."""
    from rvdjax.families import phases as ph
    from rvdjax.families.phases import LAYOUT

    sc = get_scenario("thesis-vbar")
    tset = sc.thrusters.replace(valve_s=1e-6, min_on_s=0.0)
    p, _ = sc.build(thrusters=tset)
    act = tset.actuation()
    k = 1  # approach phase, Ts = 20 s
    ts = float(p.ts[k])
    x = jnp.asarray([5.0, 30.0, 0.3, 0.01, -0.2, 0.0])
    for dv in ([0.1786, 0.0, 0.0], [-0.05, 0.12, 0.0], [0.0, 0.0, -0.0357]):
        dv = jnp.asarray(dv)
        B, c = ph.finite_burn(p, p.A[k], ts, dv[None])
        model = np.asarray(p.A[k] @ x + B[0] @ dv + c[0])
        out = _fire(act, p.plant.thrusters, LAYOUT, x, dv, ts, p.plant.mass, 0.0, jnp.zeros(6))
        truth, _ = truth_step_pulses("linear", 1, p.A[k], p.plant, None, x, out.pulses, out.g, ts)
        np.testing.assert_allclose(model, np.asarray(truth), atol=1e-5)
        impulsive = np.asarray(p.A[k] @ x + p.B[k] @ dv)
        lag = float(np.max(np.abs(impulsive - np.asarray(truth))[:3]))
        expected = float(np.max(14.0 * dv**2 / (2 * 0.5)))
        assert lag == pytest.approx(expected, rel=0.01)


def test_pwm_quantises_drops_and_carries():
    ts, valve, t_min = 2.0, 0.01, 0.05
    demand = jnp.array([0.0, 0.004, 0.006, 0.03, 0.0449, 0.051, 1.234, 2.5])
    pulses, carried, dropped = pwm(demand, ts, valve, t_min, jnp.zeros(8), carry=False)
    w = np.asarray(pulses.width[:, 0])
    np.testing.assert_allclose(w, [0, 0, 0, 0, 0, 0.05, 1.23, 2.0], atol=1e-12)
    assert list(np.asarray(dropped)) == [False, False, True, True, True, False, False, False]
    assert np.all(np.asarray(pulses.start) == 0)
    # on-time within half a valve tick of the demand, except dropped and saturated pulses
    ok = ~np.asarray(dropped) & (np.asarray(demand) <= ts)
    assert np.all(np.abs(w - np.asarray(demand))[ok] <= valve / 2 + 1e-12)
    # carry: over many periods the fired on-time tracks the demanded one within one tick
    d = jnp.asarray(RNG.uniform(0, 0.03, (200, 3)))
    c = jnp.zeros(3)
    fired = np.zeros(3)
    for k in range(200):
        p, c, _ = pwm(d[k], ts, valve, t_min, c, carry=True)
        fired += np.asarray(p.width[:, 0])
    assert np.all(np.abs(fired - np.asarray(d).sum(0)) <= t_min + valve)
    assert fired.sum() > 0.5 * float(d.sum())  # without carry nearly all would be dropped


def test_schmitt_trigger_hysteresis():
    ts, valve, t_min = 2.0, 0.01, 0.1
    demand = jnp.array([0.08, 0.05, 0.05, 0.01, 0.3])  # levels 0.8, 0.5, 0.5, 0.1, 3
    last = jnp.array([0.0, 0.0, 1.0, 1.0, 0.0])
    p, fired, dropped = schmitt(demand, ts, valve, t_min, 0.75, 0.25, last)
    np.testing.assert_allclose(p.width[:, 0], [0.1, 0.0, 0.1, 0.0, 0.3], atol=1e-12)
    np.testing.assert_array_equal(fired, [1, 0, 1, 0, 1])
    np.testing.assert_array_equal(dropped, [False, True, False, True, False])


def test_delta_sigma_equals_a_tick_by_tick_modulator():
    """The closed form against the modulator written as a loop over ticks (one half as the
    threshold, integrator of command minus fired), over several periods."""
    ts, K, T = 5.0, 50, 4
    c = jnp.asarray(RNG.uniform(-0.5, 0.5, T))
    c_ref = np.asarray(c).copy()
    total_cmd = np.zeros(T)
    total_fired = np.zeros(T)
    for _ in range(6):
        demand = RNG.uniform(0, ts, T)
        demand[0] = 0.0
        pulses, c = delta_sigma(jnp.asarray(demand), ts, c, K)
        on_ref = np.zeros((T, K))
        r = demand / ts
        for j in range(K):
            v = c_ref + r
            on_ref[:, j] = v >= 0.5
            c_ref = v - on_ref[:, j]
        np.testing.assert_array_equal(np.asarray(pulses.width) > 0, on_ref > 0)
        np.testing.assert_allclose(np.asarray(c), c_ref, atol=1e-9)
        np.testing.assert_allclose(np.asarray(pulses.start)[0], np.arange(K) * ts / K, atol=1e-12)
        total_cmd += demand
        total_fired += np.asarray(pulses.on_time())
        # the fired on-time tracks the commanded integral within one tick
        assert np.all(np.abs(total_fired - total_cmd) <= ts / K + 1e-9)


def _planar_set(**kw):
    return sets.POSEIDYN_PWM.replace(valve_s=1e-6, min_on_s=0.0, **kw)


@pytest.fixture(scope="module")
def docking_layout():
    return get_scenario("rotating-target-a").guidance_family.layout


def test_fire_delivers_the_command_in_a_rotated_body(docking_layout):
    """Nominal thrusters, fine valve: the fired mean force and torque equal the command in
    the model frame for any attitude; the nominal and applied inputs agree."""
    tset = _planar_set()
    thr, act = tset.build(), tset.actuation()
    f = jax.jit(lambda x, u: fire(act, thr, docking_layout, x, u, 2.0, 10.0, 0.0, jnp.zeros(8)))
    for theta in (0.0, 0.7, -2.5):
        x = jnp.array([1.0, 2.0, theta, 0.0, 0.0, 0.0])
        u = jnp.array([0.05, -0.12, 0.004])
        out = f(x, u)
        np.testing.assert_allclose(out.u_applied, u, atol=1e-6 * 0.15)
        np.testing.assert_allclose(out.u_nominal, out.u_applied, atol=1e-12)
        assert float(out.scale) == 1.0
        # every on-time is its thruster's share: thrust x on-time = the allocated impulse
        on = np.asarray(out.pulses.on_time())
        assert np.all((on >= 0) & (on <= 2.0))
        np.testing.assert_allclose(out.thrust_impulse, 0.15 * on.sum(), rtol=1e-12)


def test_fire_applies_faults_and_errors(docking_layout):
    tset = _planar_set(fdir=False)
    act = tset.actuation(faults=True)
    x = jnp.array([1.0, 2.0, 0.3, 0.0, 0.0, 0.0])
    u = jnp.array([0.1, 0.05, 0.0])
    healthy = _fire(
        tset.actuation(), tset.build(), docking_layout, x, u, 2.0, 10.0, 0.0, jnp.zeros(8)
    )
    used = int(np.argmax(np.asarray(healthy.pulses.on_time())))
    # stuck off from t = 5 s: fires before, not after
    thr = tset.build(fault=np.eye(8, dtype=int)[used], fault_time_s=np.full(8, 5.0))
    before = _fire(act, thr, docking_layout, x, u, 2.0, 10.0, 4.0, jnp.zeros(8))
    after = _fire(act, thr, docking_layout, x, u, 2.0, 10.0, 5.0, jnp.zeros(8))
    assert float(before.pulses.on_time()[used]) > 0
    assert float(after.pulses.on_time()[used]) == 0.0
    # stuck on: the valve is open the whole period
    thr_on = tset.build(fault=2 * np.eye(8, dtype=int)[0])
    on = _fire(act, thr_on, docking_layout, x, u, 2.0, 10.0, 0.0, jnp.zeros(8))
    assert float(on.pulses.on_time()[0]) == pytest.approx(2.0)
    # with FDIR the allocation works around the stuck-on thruster: the command is met again
    on_fdir = _fire(
        tset.actuation(fdir=True, faults=True),
        thr_on,
        docking_layout,
        x,
        u,
        2.0,
        10.0,
        0.0,
        jnp.zeros(8),
    )
    np.testing.assert_allclose(on_fdir.u_applied, u, atol=1e-6)
    assert not np.allclose(on.u_applied, u, atol=1e-3)
    # +10 % magnitude error on every thruster: the applied input is 1.1 x the nominal one
    err = _fire(
        tset.actuation(),
        tset.build(magnitude_error=0.1),
        docking_layout,
        x,
        u,
        2.0,
        10.0,
        0.0,
        jnp.zeros(8),
    )
    ref = 1.1 * np.asarray(err.u_nominal)
    np.testing.assert_allclose(err.u_applied, ref, rtol=1e-12, atol=1e-13 * np.linalg.norm(ref))


def test_thruster_set_checks_name_the_field():
    base = sets.SPOT
    with pytest.raises(ValueError, match="thrust_N"):
        base.replace(thrust_N=-1.0).build()
    with pytest.raises(ValueError, match="valve_s"):
        base.replace(valve_s=0.0).build()
    with pytest.raises(ValueError, match="fault"):
        base.build(fault=np.full(8, 3))
    with pytest.raises(ValueError, match="modulator"):
        base.replace(modulator="bang-bang").actuation()
    with pytest.raises(ValueError, match="direction"):
        ThrusterSet("x", position_m=((0, 0, 0),), direction=((0, 0, 0),)).build()


# ------------------------------------------------------------------------ closed loops


@pytest.fixture(scope="module")
def rotating_flights():
    """rotating-target-a with thrusters (healthy, and one thruster stuck off unnoticed),
    one compiled program, vmapped over the two parameter sets."""
    sc = get_scenario("rotating-target-a")
    loop = sc.loop(thrusters=sc.thrusters.replace(fdir=False), faults=True, n_steps=80)
    p_ok, x0 = sc.build(thrusters=True)
    fault = np.zeros(8, int)
    fault[0] = 1
    p_bad = with_plant(p_ok, thrusters=sc.thrusters.build(fault=fault))
    params = jax.tree.map(lambda a, b: jnp.stack([a, b]), p_ok, p_bad)
    run = jax.jit(jax.vmap(lambda p: fly(loop, p, x0)))
    infos, m = run(params)
    return sc, loop, p_ok, jax.tree.map(np.asarray, infos), jax.tree.map(np.asarray, m)


def test_closed_loop_with_thrusters_docks_and_counts_its_pulses(rotating_flights):
    sc, loop, p, infos, m = rotating_flights
    assert m.docked[0]
    active = infos.active[0]
    width = infos.pulses.width[0][active]  # (steps, T, P)
    thrust = np.asarray(p.plant.thrusters.thrust)
    # the figures recomputed from the step records
    assert m.thruster_impulse_N_s[0] == pytest.approx((width.sum(-1) * thrust).sum(), rel=1e-12)
    assert m.valve_openings[0] == int((width > 0).sum())
    assert m.propellant_kg[0] == pytest.approx(m.thruster_impulse_N_s[0] / (60.0 * G0), rel=1e-12)
    # on-times are whole valve ticks and never longer than the period
    ticks = width / 0.01
    np.testing.assert_allclose(ticks, np.round(ticks), atol=1e-6)
    assert width.sum(-1).max() <= 2.0 + 1e-12
    # the fired impulse of each step equals the commanded one within one valve tick per
    # thruster (no pulse was dropped here: the minimum on-time is one tick)
    assert m.pulses_dropped[0] == 0
    u, u_cmd = infos.u[0][active], infos.u_cmd[0][active]
    per_step = np.abs(u - u_cmd)[:, :2] * 2.0  # force impulse error [N s]
    assert per_step.max() <= 8 * 0.15 * 0.01 / 2 + 1e-9
    # every pulse centred in its period (the set's alignment)
    start = infos.pulses.start[0][active]
    on = width > 0
    np.testing.assert_allclose((start + width / 2)[on], 1.0, atol=1e-12)
    # the per-phase figures add up to the run's, phase by phase from the step records
    phase = infos.phase[0][active]
    per_step_imp = (width.sum(-1) * thrust).sum(-1)
    for k in range(2):
        assert m.phase_thruster_impulse_N_s[0, k] == pytest.approx(per_step_imp[phase == k].sum())
    assert m.phase_thruster_impulse_N_s[0].sum() == pytest.approx(m.thruster_impulse_N_s[0])
    assert m.phase_effort_l1_N_s[0].sum() == pytest.approx(m.effort_l1_N_s[0])


def test_a_thruster_stuck_off_never_fires(rotating_flights):
    _, _, _, infos, m = rotating_flights
    width = infos.pulses.width[1]
    assert width[:, 0].max() == 0.0
    assert width[:, 1:].max() > 0.0
    # the healthy vehicle fired that thruster
    assert infos.pulses.width[0][:, 0].max() > 0.0
    assert np.all(np.isfinite(m.effort_l1_N_s))


# ------------------------------------------------------------------------ command line


@pytest.mark.slow  # the thrusters' closed loop is checked above; this is the command's output
def test_run_with_thrusters_prints_both_plants(capsys, tmp_path):
    from rvdjax.cli import main

    plot = tmp_path / "run.png"
    assert main(["run", "poseidyn-lqmpc", "--thrusters", "--json", "--plot", str(plot)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["docked"] and out["ideal_forces"]["docked"]
    assert out["thrusters"].startswith("POSEIDYN")
    # delta-sigma pulses: whole 0.1 s ticks of 0.15 N thrusters
    assert out["thruster_impulse_N_s"] == pytest.approx(
        0.015 * round(out["thruster_impulse_N_s"] / 0.015), abs=1e-9
    )
    assert out["valve_openings"] > 0 and out["ideal_forces"]["valve_openings"] == 0
    assert out["effort_l1_N_s"] != out["ideal_forces"]["effort_l1_N_s"]
    assert any("delta-sigma" in a for a in out["assumptions"])
    firings = tmp_path / "run-firings.png"
    assert firings.stat().st_size > 10_000 and plot.stat().st_size > 10_000


@pytest.mark.parametrize(
    "args, word",
    [
        (["run", "poseidyn-lqmpc", "--thrusters", "--study", "x", "--run", "0"], "--thrusters"),
        (["study", "montecarlo", "spot-2d-a", "--fault", "0:stuck-off", "--out", "o"], "--fault"),
        (
            [
                "study",
                "montecarlo",
                "spot-2d-a",
                "--thrusters",
                "--fault",
                "9:stuck-off",
                "--out",
                "o",
            ],
            "thruster index",
        ),
        (
            [
                "study",
                "montecarlo",
                "spot-2d-a",
                "--thrusters",
                "--fault",
                "0:broken",
                "--out",
                "o",
            ],
            "stuck-off or stuck-on",
        ),
        (
            [
                "study",
                "montecarlo",
                "spot-2d-a",
                "--vary",
                "thruster_valve_s=uniform(0,1)",
                "--out",
                "o",
            ],
            "thruster_valve_s",
        ),
    ],
)
def test_thruster_options_fail_before_any_work(args, word, capsys, tmp_path, monkeypatch):
    import jax.monitoring

    from rvdjax.cli import main

    monkeypatch.chdir(tmp_path)
    # the work that must not start is compiling a closed loop: count XLA compiles (a wall
    # clock limit read the machine's load instead)
    compiles, listening = [], [True]

    def listen(event, seconds, **kwargs):
        if listening[0] and event.endswith("backend_compile_duration"):
            compiles.append(seconds)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        assert main(args) == 2
    finally:
        listening[0] = False
    assert word in capsys.readouterr().err
    assert sum(compiles) < 1.0, f"{len(compiles)} compiles ({sum(compiles):.1f} s) before the error"


@pytest.mark.slow  # a study end to end (19 s): faults are checked by test_fire_applies_faults...
def test_study_with_a_failed_thruster_replays(tmp_path, capsys):
    """A Monte Carlo study with thrusters and a stuck-off thruster: its table carries the
    thruster figures, and a run replayed alone gives the same figures."""
    import pandas as pd

    from rvdjax.cli import main

    out = tmp_path / "st"
    args = ["study", "montecarlo", "spot-2d-a-free", "--runs", "3", "--thrusters", "--fault"]
    args += ["2:stuck-off", "--vary", "x0[0]=+normal(0,0.05)", "--slots", "4", "--chunk", "4"]
    assert main([*args, "--out", str(out), "--quiet"]) == 0
    table = pd.read_parquet(out / "runs")
    assert len(table) == 3 and (table["valve_openings"] > 0).all()
    capsys.readouterr()
    assert main(["run", "spot-2d-a-free", "--study", str(out), "--run", "1", "--json"]) == 0
    replay = json.loads(capsys.readouterr().out)
    row = table.set_index("run").loc[1]
    assert replay["thruster_impulse_N_s"] == pytest.approx(row["thruster_impulse_N_s"], rel=1e-9)
    assert replay["valve_openings"] == row["valve_openings"]
    assert replay["thrusters"].startswith("SPOT RED")


def test_tuner_judges_with_the_thrusters():
    """``judge_thrusters``: the held-out evaluation flies the thruster plant (valve pulses
    counted), the same tuning values applied to it."""
    from rvdjax.tune import LossWeights, Tuner, TuneSpec
    from rvdjax.tune.trainer import _run_set

    spec = TuneSpec(
        scenario="poseidyn-lqmpc",
        params=("R",),
        train=2,
        heldout=2,
        steps=0,
        n_steps=12,
        judge_thrusters=True,
    )
    tuner = Tuner(spec)
    x, k = _run_set(spec, tuner.scenario, 2, 1)
    theta = tuner.space.theta()
    refs = (jnp.ones(()), jnp.ones(()))
    L, m = tuner.losses(theta, x, k, refs, LossWeights(), 2, thrusters=True)
    assert np.all(np.isfinite(L)) and np.all(m.valve_openings > 0)
    # the tuned values reach the thruster plant: another R fires other pulses
    other = {**theta, "R": theta["R"] + 1.0}
    _, m2 = tuner.losses(other, x, k, refs, LossWeights(), 2, thrusters=True)
    assert not np.array_equal(m2.thruster_impulse_N_s, m.thruster_impulse_N_s)


def test_pair_groups_equal_the_lp_without_torque():
    """Paper 001's set flies a torque-free family: the pair-group closed form (alike thrusters
    sharing a direction's thrust equally) gives the LP's least total thrust and scale, and no
    torque, for random demands, saturated ones included."""
    from rvdjax.actuators.allocation import allocate
    from rvdjax.actuators.thrusters import effectiveness

    sc = get_scenario("poseidyn-lqmpc")
    tset = sc.thrusters.replace(valve_s=1e-9, min_on_s=0.0, modulator="pwm")
    thr, act = tset.build(), tset.actuation()
    lay = sc.guidance_family.layout
    M = effectiveness(thr.position, thr.direction)[jnp.asarray(act.rows)]
    demands = jnp.asarray(RNG.uniform(-0.45, 0.45, (200, 2)))  # up to 1.5x the 0.3 N per axis

    def both(u):
        out = fire(act, thr, lay, jnp.zeros(4), u, 5.0, 10.0, 0.0, jnp.zeros(8))
        f = out.pulses.on_time() * thr.thrust / 5.0
        lp = allocate(M, jnp.concatenate([u, jnp.zeros(1)]), thr.thrust)
        return f, out.scale, lp.f, lp.scale

    f, s, f_lp, s_lp = jax.jit(jax.vmap(both))(demands)
    np.testing.assert_allclose(s, s_lp, atol=1e-9)
    assert 0.2 < float(np.mean(np.asarray(s) < 1)) < 0.8  # saturated and unsaturated demands
    np.testing.assert_allclose(f.sum(-1), f_lp.sum(-1), rtol=1e-6, atol=1e-9)
    wrench = np.asarray(f) @ np.asarray(M).T
    np.testing.assert_allclose(wrench[:, :2], np.asarray(s)[:, None] * demands, atol=1e-6)
    np.testing.assert_allclose(wrench[:, 2], 0.0, atol=1e-9)
