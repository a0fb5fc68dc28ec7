"""Modulators: each thruster's mean force over a control period -> its valve pulses.

A thruster is on or off. Over a control period Ts the guidance asks thruster i for a mean
force f_i (the allocation, :mod:`rvdjax.actuators.allocation`), i.e. an on-time f_i Ts / F_i at
full thrust F_i. The modulators here turn that into pulses ``(start, width)`` inside the period
(times from the period's start [s], P pulses per thruster, a width of 0 for none) and keep
their own state between periods (in the loop state, so batches, studies and replays carry it):

* :func:`pwm`: one pulse per period, its width rounded to the valve resolution and capped at
  Ts, from the period's start (``align="start"``) or centred in the period
  (``align="centre"``). A pulse shorter than the minimum on-time is dropped (paper 003
  Sec. 2.1.2, Eq. 2.6: "the control is simply discarded"); with ``carry`` the impulse lost to
  rounding or to a dropped pulse is added to the next period's command (error feedback,
  state: the carried on-time [s]).
* :func:`schmitt`: PWM whose pulses shorter than the minimum on-time fire at the minimum
  on-time when their length is above ``on`` times it, or above ``off`` times it while the
  thruster fired in the previous period, else not (Basilisk's thrFiringSchmitt; state: 1.0
  if the thruster fired last period).
* :func:`delta_sigma`: paper 001's modulator (its ref. [4]): the period is split into K
  ticks of Ts / K; at each tick the integrator of (command - fired) in units of one tick's
  pulse opens the valve when it reaches one half, so the fired pulses track the command's
  integral within half a tick's impulse at every tick and carry the remainder into the next
  period (state: the integrator). For a command held over the period this first-order
  loop has the closed form n_j = floor(c + j r + 1/2) pulses after j ticks (c: integrator at
  the start, r = f / F), which is what is computed (no scan over ticks).

All are pure functions of arrays (jit / vmap); the pulse shapes are static (P = 1 or K).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

__all__ = ["Pulses", "pwm", "schmitt", "delta_sigma", "on_time_demand", "ALIGNMENTS"]

#: Where a PWM / Schmitt pulse sits in its period. "start": it opens when the command arrives,
#: so its impulse acts as early as it can (an impulsive model, paper 003 Eq. 3.1, puts the
#: delta-v at the period's start). "centre": centred on Ts / 2, where a zero-order-hold model
#: puts the centroid of the period's impulse; for a double integrator the state reached at
#: the period's end is then exactly the model's, whatever the pulse's width (position
#: v Ts + dv (Ts - c) with c the pulse's centre: c = Ts / 2 for both).
ALIGNMENTS = ("start", "centre")


class Pulses(NamedTuple):
    """Valve pulses of one control period: (T, P) start times and widths [s]."""

    start: jnp.ndarray
    width: jnp.ndarray

    def on_time(self):
        """(T,) total on-time of each thruster [s]."""
        return jnp.sum(self.width, axis=-1)

    def openings(self):
        """(T,) number of valve openings (pulses of non-zero width)."""
        return jnp.sum(self.width > 0, axis=-1)


def on_time_demand(f, thrust, ts):
    """(T,) on-time [s] that gives the mean force ``f`` [N] over ``ts`` at full ``thrust``."""
    safe = jnp.where(thrust > 0, thrust, 1.0)
    return jnp.where(thrust > 0, f * ts / safe, 0.0)


def _quantise(t, valve_s, ts):
    """On-time rounded to the valve resolution, within [0, floor(ts / valve) valve]."""
    n_max = jnp.floor(ts / valve_s + 1e-9)
    return jnp.clip(jnp.round(t / valve_s), 0.0, n_max) * valve_s


def _placed(w, ts, align: str):
    """Pulses (T, 1) of widths ``w`` placed in the period by ``align`` (:data:`ALIGNMENTS`)."""
    start = jnp.zeros_like(w) if align == "start" else 0.5 * (ts - w)
    return Pulses(start[:, None], w[:, None])


def pwm(t_demand, ts, valve_s, min_on_s, carried, carry: bool, align: str = "start"):
    """One pulse per thruster, from the period's start or centred in it (``align``).

    Args:
        t_demand: (T,) on-time asked for [s].
        ts: () control period [s]. valve_s, min_on_s: () [s].
        carried: (T,) on-time carried from earlier periods [s] (zeros without ``carry``).
        carry: static; keep the lost on-time for the next period.
        align: static, :data:`ALIGNMENTS`.

    Returns:
        (Pulses with P = 1, carried', dropped (T,) bool: a non-zero pulse under the minimum
        on-time was not fired).
    """
    want = t_demand + (carried if carry else 0.0)
    w = _quantise(want, valve_s, ts)
    dropped = (w > 0) & (w < min_on_s - 1e-12)
    w = jnp.where(dropped, 0.0, w)
    if carry:  # what saturation cut off is not carried: only rounding and dropped pulses
        carried_next = jnp.clip(want - w, -valve_s, jnp.maximum(min_on_s, valve_s))
    else:
        carried_next = jnp.zeros_like(carried)
    return _placed(w, ts, align), carried_next, dropped


def schmitt(t_demand, ts, valve_s, min_on_s, on_level, off_level, fired_last, align="start"):
    """PWM with a Schmitt trigger on pulses shorter than the minimum on-time.

    Returns:
        (Pulses with P = 1, fired (T,) 1.0 where the thruster fired, dropped (T,) bool).
    """
    w = _quantise(t_demand, valve_s, ts)
    short = w < min_on_s - 1e-12
    level = t_demand / jnp.maximum(min_on_s, 1e-300)
    hold = fired_last > 0.5
    fire_min = (level >= on_level) | (hold & (level >= off_level))
    w_min = _quantise(min_on_s, valve_s, ts)
    w = jnp.where(short, jnp.where(fire_min & (t_demand > 0), w_min, 0.0), w)
    dropped = short & (t_demand > 0) & (w == 0)
    fired = (w > 0).astype(w.dtype)
    return _placed(w, ts, align), fired, dropped


def delta_sigma(t_demand, ts, integrator, ticks: int):
    """First-order delta-sigma modulation on K = ``ticks`` ticks of the period.

    Args:
        t_demand: (T,) on-time asked for [s] (clipped to [0, ts]).
        integrator: (T,) the integrator in tick pulses, in [-1/2, 1/2).
        ticks: static K.

    Returns:
        (Pulses with P = K: tick j's pulse starts at j Ts / K and lasts Ts / K or 0,
        integrator').
    """
    dt = ts / ticks
    r = jnp.clip(t_demand / ts, 0.0, 1.0)
    j = jnp.arange(ticks + 1, dtype=r.dtype)
    n = jnp.floor(integrator[:, None] + j[None, :] * r[:, None] + 0.5)
    on = jnp.diff(n, axis=-1)  # (T, K) in {0, 1}
    start = jnp.broadcast_to(j[:-1] * dt, on.shape)
    integ = integrator + ticks * r - n[:, -1]
    return Pulses(start, on * dt), integ
