"""One control period of the thrusters: command -> allocation -> modulation -> fired pulses.

:func:`fire` takes the guidance's command in the family's units (a force held over Ts, or a
delta-v), turns it into the mean wrench over the period in the body frame, allocates it to
the thrusters (:mod:`rvdjax.actuators.allocation`: the least total thrust, or with
``allocation="separate"`` a pure force by opposing pairs plus a pure couple), modulates each
thruster's mean force into valve pulses (:mod:`rvdjax.actuators.modulation`), applies the
faults, and returns the pulses with each thruster's generalised force in the model frame
(actual: magnitude error, misalignment, Gauss-Markov thrust error; nominal: what the flight
software believes it fired), ready for the truth (:mod:`rvdjax.actuators.response`).

Assumptions (printed by ``rvdjax run`` with thrusters on):

* the body-to-model rotation is the attitude at the period's start, held over the period
  (planar vehicles; it turns by omega Ts, below 4 deg a period in the papers' cases), and
  the allocation uses the true attitude (no attitude-knowledge error);
* a fault acts from the first period that starts at or after its time; with ``fdir`` the
  allocation knows it from then on;
* the torque of a family without a torque input (paper 001: attitude held by a slew and PD
  loop outside the MPC) is demanded as zero and the attitude's own firings are not modelled.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from rvdjax.actuators.allocation import Allocation, allocate, allocate_pairs
from rvdjax.actuators.modulation import Pulses, delta_sigma, on_time_demand, pwm, schmitt
from rvdjax.actuators.thrusters import (
    Actuation,
    Thrusters,
    effectiveness,
    misaligned_directions,
    rotation_z,
)

__all__ = ["Fired", "fire", "wrench_rows", "FIRE_NOTES"]

FIRE_NOTES = (
    "thrusters: the body-to-model rotation is the attitude at the start of each control "
    "period, held over it; the allocation uses the true attitude",
    "thrusters: PWM and Schmitt pulses open when the command arrives (the set's alignment "
    "'start') or are centred in the control period ('centre'), delta-sigma pulses are whole "
    "ticks; a fault acts from the first period starting at or after its time",
)


class Fired(NamedTuple):
    """What the thrusters did over one control period.

    Attributes:
        pulses: the truth's pulses (faults applied), (T, P) [s].
        g: (T, nu) actual generalised force of each thruster while open, model frame.
        u_applied: (nu,) the period's mean input in the family's units (force: mean force
            [N, N m]; delta-v: the fired delta-v [m/s]) — what the truth received.
        u_nominal: (nu,) the same from the commanded pulses and the nominal thrusters (what
            the flight software believes it applied).
        thrust_impulse: () sum over thrusters of thrust x on-time [N s] (paper 002 Eq. 11).
        openings: () valve openings.
        dropped: () pulses dropped by the minimum on-time.
        scale: () fraction of the demand the allocation met (1: not saturated).
        mod: (T,) the modulator's state after the period.
    """

    pulses: Pulses
    g: jnp.ndarray
    u_applied: jnp.ndarray
    u_nominal: jnp.ndarray
    thrust_impulse: jnp.ndarray
    openings: jnp.ndarray
    dropped: jnp.ndarray
    scale: jnp.ndarray
    mod: jnp.ndarray


def wrench_rows(layout) -> tuple[tuple[int, int], ...]:
    """(input index, wrench row) pairs: force inputs to rows 0, 1(, 2), the torque to 5."""
    pairs = [(i, r) for r, i in enumerate(layout.force)]
    pairs += [(i, 5) for i in layout.torque]
    return tuple(pairs)


def _generalised(layout, R, force_body, torque_body):
    """(T, nu): per-thruster model-frame force components and torque in the input order."""
    force_model = force_body @ R.T  # (T, 3)
    cols = [None] * layout.nu
    for r, i in enumerate(layout.force):
        cols[i] = force_model[:, r]
    for i in layout.torque:
        cols[i] = torque_body[:, 2]
    return jnp.stack(cols, axis=-1)


def _pairs_exact(act: Actuation, layout) -> bool:
    """The pair-group closed form is the least-thrust allocation (static): groups of one
    thruster through the centre of mass, or alike groups, no torque input and no faults. The
    allocated rows must start with the force rows of the groups' axes."""
    n_axes = len(act.pair_groups) // 2
    if not act.pair_groups or act.rows[:n_axes] != tuple(range(n_axes)):
        return False
    if all(len(g) == 1 for g in act.pair_groups):
        return True
    return not layout.torque and not act.faults


def _pair_shares(act: Actuation, d_axes, F_alloc, dtype) -> Allocation:
    """The closed form of opposing pair groups (:func:`allocate_pairs`) with each group's
    force shared equally by its alike thrusters, so that it gives no torque."""
    groups = act.pair_groups
    F_group = jnp.stack([sum(F_alloc[i] for i in g) for g in groups])
    pair = allocate_pairs(d_axes, F_group[0::2], F_group[1::2])
    share = jnp.zeros(F_alloc.shape[0], dtype)
    for j, g in enumerate(groups):
        for i in g:
            share = share.at[i].set(pair.f[j] / len(g))
    return pair._replace(f=share)


def _full_on(ts, like):
    """The pulses of a valve stuck open for the whole period."""
    P = like.shape[-1]
    start = jnp.broadcast_to(jnp.arange(P, dtype=like.dtype) * ts / P, like.shape)
    return Pulses(start, jnp.broadcast_to(ts / P, like.shape))


def fire(
    act: Actuation,
    thr: Thrusters,
    layout,
    x,
    u_cmd,
    ts,
    mass,
    t,
    mod,
    thrust_factor=None,
) -> Fired:
    """Fly one control period's command through the thrusters.

    Args:
        act: static :class:`Actuation`.
        thr: traced :class:`Thrusters`.
        layout: the family's :class:`~rvdjax.loop.family.Layout`.
        x: (nx,) true state at the period's start (attitude for ``frame="attitude"``).
        u_cmd: (nu,) the guidance's command (force [N, N m] or delta-v [m/s]).
        ts: () control period [s]; mass: () [kg]; t: () time at the period's start [s].
        mod: (T,) modulator state.
        thrust_factor: (T,) multiplicative thrust error of each thruster (Gauss-Markov), or
            None.
    """
    dtype = jnp.result_type(u_cmd)
    T = act.n
    # the mean generalised force the period must deliver, in the family's input order
    if layout.input == "force":
        mean = u_cmd
    else:  # delta-v: impulse m dv delivered over the period
        mean = u_cmd * mass / ts
    theta = x[layout.att[0]] if act.frame == "attitude" else jnp.zeros((), dtype)
    R = rotation_z(theta)
    wrench = jnp.zeros(6, dtype)
    for i, r in wrench_rows(layout):
        wrench = wrench.at[r].set(mean[i])
    wrench = wrench.at[:3].set(R.T @ wrench[:3])  # to the body frame (rotation about z)

    if act.faults:
        faulted = t >= thr.fault_time_s
        stuck_off = faulted & (thr.fault == 1)
        stuck_on = faulted & (thr.fault == 2)
    else:
        stuck_off = stuck_on = jnp.zeros(T, bool)
    rows = jnp.asarray(act.rows, int)
    M = effectiveness(thr.position, thr.direction)[rows]  # (k, T) nominal
    d = wrench[rows]
    F_alloc = thr.thrust
    if act.fdir and act.faults:  # allocate around the failed, net of the stuck-on thrust
        F_alloc = jnp.where(stuck_off | stuck_on, 0.0, F_alloc)
        d = d - M @ jnp.where(stuck_on, thr.thrust, 0.0)
    if act.allocation == "separate":  # a pure force by pairs plus a pure couple
        n_axes = len(act.pair_groups) // 2
        force = _pair_shares(act, d[:n_axes], F_alloc, dtype)
        couple = allocate(M, d.at[:n_axes].set(0.0), F_alloc)
        f = force.f + couple.f
        over = jnp.max(f / jnp.where(F_alloc > 0, F_alloc, jnp.inf))
        shrink = 1.0 / jnp.maximum(over, 1.0)  # the whole wrench scaled: its direction kept
        alloc = Allocation(f=f * shrink, scale=jnp.minimum(force.scale, couple.scale) * shrink)
    elif _pairs_exact(act, layout):
        alloc = _pair_shares(act, d[: len(act.pair_groups) // 2], F_alloc, dtype)
    else:
        alloc = allocate(M, d, F_alloc)
    t_dem = on_time_demand(alloc.f, thr.thrust, ts)

    if act.modulator == "pwm":
        cmd, mod_next, dropped = pwm(
            t_dem, ts, thr.valve_s, thr.min_on_s, mod, act.carry, act.align
        )
    elif act.modulator == "schmitt":
        cmd, mod_next, dropped = schmitt(
            t_dem, ts, thr.valve_s, thr.min_on_s, thr.schmitt_on, thr.schmitt_off, mod, act.align
        )
    else:
        cmd, mod_next = delta_sigma(t_dem, ts, mod, act.ticks)
        dropped = jnp.zeros(T, bool)

    pulses = cmd
    if act.faults:
        full = _full_on(ts, cmd.width)
        on = stuck_on[:, None]
        off = stuck_off[:, None]
        pulses = Pulses(
            jnp.where(on, full.start, cmd.start),
            jnp.where(off, 0.0, jnp.where(on, full.width, cmd.width)),
        )

    factor = jnp.ones(T, dtype) if thrust_factor is None else thrust_factor
    thrust_true = thr.thrust * (1.0 + thr.magnitude_error) * factor
    d_true = misaligned_directions(thr)
    g_true = _generalised(
        layout,
        R,
        thrust_true[:, None] * d_true,
        thrust_true[:, None] * jnp.cross(thr.position, d_true),
    )
    g_nom = _generalised(
        layout,
        R,
        thr.thrust[:, None] * thr.direction,
        thr.thrust[:, None] * jnp.cross(thr.position, thr.direction),
    )
    on_true, on_cmd = pulses.on_time(), cmd.on_time()
    if layout.input == "force":
        u_applied = on_true @ g_true / ts
        u_nominal = on_cmd @ g_nom / ts
    else:
        u_applied = on_true @ g_true / mass
        u_nominal = on_cmd @ g_nom / mass
    return Fired(
        pulses=pulses,
        g=g_true,
        u_applied=u_applied,
        u_nominal=u_nominal,
        thrust_impulse=jnp.sum(thrust_true * on_true),
        openings=jnp.sum(pulses.openings()),
        dropped=jnp.sum(dropped),
        scale=alloc.scale,
        mod=mod_next,
    )
