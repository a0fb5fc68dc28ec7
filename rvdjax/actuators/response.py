"""The truth under valve pulses: piecewise-constant thrust inside a control period.

Linear models (CW, the planar double integrators): superposition is exact. For x' = Ac x +
Bc u(t) with u(t) = sum_i g_i [s_i <= t < s_i + w_i] (thruster i's generalised force g_i
while its valve is open),

    x(Ts) = e^{Ac Ts} x(0)
            + sum_i sum_{k>=0} Ac^k Bc g_i ((Ts - s_i)^{k+1} - (Ts - s_i - w_i)^{k+1}) / (k+1)!

(the integral of e^{Ac (Ts - s)} Bc g_i over each pulse, expanded in powers of Ac). The series
is evaluated by Horner's rule with :data:`N_TERMS` terms: for the double integrators Ac^2 = 0
and it ends after two; for CW the k-th term is of order Ts^2 (n Ts)^(k-1) / (k+1)!, which with
n Ts <= 0.1 (:func:`check_series`; a 60 s period in LEO is 0.07) is below float64 rounding
by the last term. The same expression at a time tau < Ts (pulses clipped to tau) gives the
states inside the period.

Nonlinear truths (two-body, J2, drag): the period is cut at every valve closing into
constant-thrust segments, each integrated by RK4 (:func:`rvdjax.propagate.propagate_step`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from rvdjax.actuators.modulation import Pulses

__all__ = ["N_TERMS", "pulse_response", "pulse_states", "pulse_segments", "check_series"]

N_TERMS = 10


def _powers(a):
    """(K, ...) a^{k+1} / (k+1)! for k < N_TERMS, by a running product (a power function
    would cost an exp and a log per element)."""
    k1 = jnp.arange(1, N_TERMS + 1, dtype=a.dtype).reshape((-1,) + (1,) * a.ndim)
    return jnp.cumprod(jnp.broadcast_to(a[None], (N_TERMS, *a.shape)) / k1, axis=0)


def pulse_response(Ac, Bc, tau, pulses: Pulses, g, grid: bool = False):
    """(nx,) forced response at time ``tau`` [s] after the period's start (x(0) = 0).

    Args:
        Ac: (nx, nx) continuous state matrix; Bc: (nx, nu) continuous input matrix (per unit
            of the generalised force: N, N m).
        tau: () time from the period's start [s].
        pulses: (T, P) starts and widths [s].
        g: (T, nu) generalised force of each thruster while open, model frame [N, N m].
        grid: static; the pulses are whole ticks of one grid shared by every thruster (the
            delta-sigma modulator: start[i, p] = p Ts / P, width 0 or Ts / P), so the
            moments are one matrix product with the grid's.
    """
    if grid:
        P = pulses.start.shape[-1]
        s0 = jnp.minimum(pulses.start[0], tau)
        tick = jnp.max(pulses.start[0, 1:] - pulses.start[0, :-1]) if P > 1 else tau
        s1 = jnp.minimum(pulses.start[0] + tick, tau)
        W = _powers(tau - s0) - _powers(tau - s1)  # (K, P)
        on = pulses.width / jnp.where(tick > 0, tick, 1.0)  # (T, P): 0 or 1
        mom = W @ on.T  # (K, T)
    else:
        s0 = jnp.minimum(pulses.start, tau)
        s1 = jnp.minimum(pulses.start + pulses.width, tau)
        # moments (K, T): sum over pulses of (a^{k+1} - b^{k+1}) / (k+1)!, a >= b >= 0
        mom = jnp.sum(_powers(tau - s0) - _powers(tau - s1), axis=-1)
    c = jnp.einsum("kt,tu->ku", mom, g) @ Bc.T  # (K, nx): Bc g-moments
    out = c[-1]
    for j in range(N_TERMS - 2, -1, -1):  # Horner: c_0 + Ac (c_1 + Ac (c_2 + ...))
        out = c[j] + Ac @ out
    return out


def pulse_states(Ac, Bc, x, taus, pulses: Pulses, g, grid: bool = False):
    """(M, nx) linear truth at the times ``taus`` (M,) [s] inside the period, from ``x`` at
    its start under ``pulses``: e^{Ac tau} x plus :func:`pulse_response` at tau (the pulses'
    own path, not the model's mean input)."""
    from rvdjax.dynamics import zoh_states

    free = zoh_states(Ac, Bc, x, jnp.zeros(Bc.shape[1], x.dtype), taus)
    forced = jax.vmap(lambda tau: pulse_response(Ac, Bc, tau, pulses, g, grid))(taus)
    return free + forced


def pulse_segments(pulses: Pulses, g, ts, from_start: bool = True):
    """Constant-thrust segments of a period with one pulse per thruster (PWM, Schmitt).

    Args:
        from_start: static; every pulse starts at the period's beginning (the segments are
            then cut at the valve closings only: T + 1 of them); False: anywhere in the
            period (cut at every opening and closing: 2 T + 1 segments).

    Returns:
        (durations (S,) [s], forces (S, nu)): the segments in time order, each with the sum
        of the generalised forces of the thrusters open during it.
    """
    start = jnp.clip(pulses.start[:, 0], 0.0, ts)
    ends = jnp.minimum(start + pulses.width[:, 0], ts)
    cuts = ends if from_start else jnp.concatenate([start, ends])
    bounds = jnp.concatenate([jnp.zeros((1,), ends.dtype), jnp.sort(cuts), jnp.reshape(ts, (1,))])
    durations = jnp.diff(bounds)
    # thruster i is open during segment j when it opened by the segment's start and closes
    # at or after its end
    open_ = (start[None, :] <= bounds[:-1, None]) & (ends[None, :] >= bounds[1:, None])
    open_ = open_ & (pulses.width[:, 0] > 0)[None, :]
    forces = open_.astype(g.dtype) @ g
    return durations, forces


def check_series(Ac, ts) -> None:
    """ValueError unless the series of :func:`pulse_response` is exact to rounding for a
    control period ``ts`` [s]: spectral radius of Ac times the longest period <= 0.1."""
    import numpy as np

    rho = float(np.max(np.abs(np.linalg.eigvals(np.asarray(Ac, float)))))
    longest = float(np.max(np.asarray(ts, float)))
    if rho * longest > 0.1:
        raise ValueError(
            f"thrusters: control period {longest:g} s is too long for the pulse response "
            f"series (spectral radius {rho:.3g} rad/s x period must be <= 0.1)"
        )
