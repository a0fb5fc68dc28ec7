"""The actuator path of a closed-loop step: from the guidance's command to the input the
truth integrates, and the truth's step under it.

Three paths (:class:`~rvdjax.loop.kernel.LoopConfig`): the vehicle's thrusters
(``actuation``: allocation, modulation into valve pulses, per-thruster Gauss-Markov thrust
error when ``disturbed``; the truth integrates the pulses), ideal forces with disturbances
(minimum impulse bit and Gauss-Markov thrust error per input axis), or ideal forces applied
exactly. A verification's dispersion may scale the truth's input of the ideal-force paths
(``Draws.input_scale``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import jax.numpy as jnp

from rvdjax.actuators.fire import Fired, fire
from rvdjax.actuators.response import pulse_states
from rvdjax.disturbances import gm_step, minimum_impulse_bit, thrust_factor
from rvdjax.loop.plant import impulse_per_unit, truth_step, truth_step_pulses

if TYPE_CHECKING:
    from rvdjax.loop.kernel import Loop, LoopConfig

__all__ = ["Actuated", "actuate", "truth_path"]


class Actuated(NamedTuple):
    """A command after the actuators.

    Attributes:
        u: (nu,) the input the truth receives (the mean input over the step with thrusters;
            zero for a finished run).
        u_believed: (nu,) the input the navigation filter predicts with: the command after
            the on-board logic (modulation, minimum impulse bit), before the thrust errors.
        gm: (n, 2) the Gauss-Markov thrust-error states for the next step.
        fired: with thrusters, the period's :class:`~rvdjax.actuators.fire.Fired` (pulses,
            per-thruster forces, impulse, openings, modulator state); None otherwise.
    """

    u: jnp.ndarray
    u_believed: jnp.ndarray
    gm: jnp.ndarray
    fired: Fired | None


def actuate(config: LoopConfig, layout, plant, x, t, k, key, gm, mod, u_cmd, dt, active):
    """The command ``u_cmd`` over a step of ``dt`` [s] through the actuators.

    Args:
        config: the loop's static configuration (``actuation``, ``disturbed``).
        layout: the family's :class:`~rvdjax.loop.family.Layout`.
        plant: the :class:`~rvdjax.loop.plant.Plant` (``thrusters``, ``disturbances``,
            ``mass`` [kg]).
        x: (nx,) true state at the step's start; t: () its time [s]; k: () the step index.
        key: the step's actuator PRNG key (used only when ``config.disturbed``).
        gm: (n, 2) Gauss-Markov thrust-error states; mod: (T,) modulator state or None.
        u_cmd: (nu,) the guidance's command; active: () the run is in progress.

    Returns:
        :class:`Actuated`.
    """
    u = u_cmd
    u_believed = u_cmd
    fired = None
    if config.actuation is not None:
        factor = None
        if config.disturbed:
            factor = thrust_factor(gm)
            gm = gm_step(key, gm, plant.disturbances, dt, k=k)
        thr = plant.thrusters
        fired = fire(config.actuation, thr, layout, x, u_cmd, dt, plant.mass, t, mod, factor)
        u = jnp.where(active, fired.u_applied, 0.0)
        # the modulation is on-board logic (known to the filter), the thrust errors are not
        u_believed = fired.u_nominal
    elif config.disturbed:
        d = plant.disturbances
        per_u = impulse_per_unit(layout, plant.mass, dt)
        idx = jnp.asarray(layout.force, int)
        u = u.at[idx].set(minimum_impulse_bit(u[idx] * per_u, d) / per_u)
        # the minimum impulse bit is on-board logic (known to the filter); the thrust factor
        # (1 + w / 100) is not: the filter predicts with the command after the former only
        u_believed = u
        u = u * thrust_factor(gm)
        gm = gm_step(key, gm, d, dt, k=k)
    scale = _input_scale(plant)
    if scale is not None and config.actuation is None:  # a truth-only mass / inertia error
        u = u * scale
    return Actuated(u, u_believed, gm, fired)


def truth_path(loop: Loop, params, A, B, orbit, x, act: Actuated, dt, active):
    """The truth's step under the actuated input: (x_next, orbit_next, taus, subs).

    ``A``, ``B``: the truth's discrete model of the step; ``orbit``: the target's inertial
    state (nonlinear truths) or None; ``x``: (nx,) true state at the step's start. With
    thrusters the truth integrates the valve pulses, otherwise the input held over ``dt``.
    ``taus`` (S,) [s] and ``subs`` (S, nx) are the family's sub-samples of the step (the
    pulses' path with thrusters on the linear truth; empty for a family without them).
    """
    fam, fc, cfg, lay = loop.family, loop.config.family_config, loop.config, loop.family.layout
    fired = act.fired
    if fired is None:
        x_next, orbit_next = truth_step(
            lay, cfg.truth, cfg.truth_substeps, A, B, params.plant, orbit, x, act.u, dt
        )
    else:
        g_fired = jnp.where(active, fired.g, 0.0)
        x_next, orbit_next = truth_step_pulses(
            cfg.truth,
            cfg.truth_substeps,
            A,
            params.plant,
            orbit,
            x,
            fired.pulses,
            g_fired,
            dt,
            grid=cfg.actuation.modulator == "delta-sigma",
            from_start=cfg.actuation.align == "start",
        )
    if fam.subsamples is not None:
        taus, subs = fam.subsamples(params, fc, x, act.u, dt)
        if fired is not None and cfg.truth == "linear":  # the pulses' path, not the mean input's
            subs = pulse_states(
                params.plant.Ac,
                params.plant.Bc,
                x,
                taus,
                fired.pulses,
                g_fired,
                grid=cfg.actuation.modulator == "delta-sigma",
            )
    else:
        taus, subs = jnp.zeros((0,), x.dtype), jnp.zeros((0, lay.nx), x.dtype)
    return x_next, orbit_next, taus, subs


def _input_scale(plant):
    """The truth's input multiplier of a verification's dispersion (Draws.input_scale)."""
    d = plant.disturbances
    draws = None if d is None else d.draws
    return None if draws is None else draws.input_scale
